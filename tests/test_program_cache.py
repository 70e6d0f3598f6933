"""The program cache (hds.utils.runtime): the trainer's lowered program kept across processes
by jax.export, under a key of everything it is built from."""

from __future__ import annotations

import sys

import jax
import numpy as np
import pytest

from hds.envs import make_env
from hds.experiment import batch_hparams, compiled_programs
from hds.utils import runtime
from hds.utils.runtime import RunByRun, Unhashable, fingerprint, program_key
from tests.conftest import TINY, make_config


@pytest.fixture(scope="module")
def tiny():
    from hds.algo.pods import make_train_from_config

    cfg = make_config(*TINY)
    trainer = make_train_from_config(cfg, make_env(cfg.env))
    return cfg, trainer


def chunk_outputs(run_chunk, trainer, cfg):
    hparams = batch_hparams(cfg, trainer)
    init, _, keys, hparams = compiled_programs(cfg, trainer, hparams)
    state = init(keys, hparams)
    return jax.tree.leaves(run_chunk.lower(state, hparams).compile()(state, hparams))


def test_a_hit_skips_tracing_and_gives_the_numbers_of_jit_to_the_last_digit(
    tiny, tmp_path, monkeypatch
):
    cfg, trainer = tiny
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    key = program_key(cfg, trainer.run_chunk)
    assert key is not None
    plain = chunk_outputs(RunByRun(trainer.run_chunk), trainer, cfg)  # no key: jax.jit
    miss = chunk_outputs(RunByRun(trainer.run_chunk, key=key), trainer, cfg)
    entries = sorted(p.name for p in tmp_path.iterdir())
    assert len(entries) == 2  # the serialized program and its output structure

    traced = []

    def never(*args):  # a hit deserializes the program: the function is not traced
        traced.append(args)
        return trainer.run_chunk(*args)

    hit = chunk_outputs(RunByRun(never, key=key), trainer, cfg)
    assert not traced and sorted(p.name for p in tmp_path.iterdir()) == entries
    for a, b, c in zip(plain, miss, hit, strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(b), np.asarray(c))


def test_a_changed_config_closure_or_source_file_changes_the_key(tiny, tmp_path, monkeypatch):
    from hds.algo.pods import make_train_from_config

    cfg, trainer = tiny
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    key = program_key(cfg, trainer.run_chunk)
    assert program_key(cfg, trainer.run_chunk) == key  # deterministic
    other = make_config(*TINY, "algo.learning_rate=2e-3")
    assert program_key(other, trainer.run_chunk) != key
    # the same config, another env inside the closure (exact effects, as a plant's)
    env = make_env(cfg.env, sharpness=None)
    assert program_key(cfg, make_train_from_config(cfg, env).run_chunk) != key
    monkeypatch.setattr(runtime, "source_digest", lambda: "an edited source file")
    assert program_key(cfg, trainer.run_chunk) != key


def test_an_edited_function_outside_hds_changes_its_fingerprint():
    def force(v):  # a user's effect, edited in place between two runs
        return -2.0 * v

    def edited(v):
        return -3.0 * v

    edited.__qualname__ = force.__qualname__
    assert fingerprint(force) != fingerprint(edited)
    assert fingerprint(force) == fingerprint(force)


def test_no_key_where_the_cache_is_off_or_a_closure_cannot_be_hashed(tiny, monkeypatch):
    cfg, trainer = tiny
    monkeypatch.setenv("HDS_PROGRAM_CACHE", "off")
    assert program_key(cfg, trainer.run_chunk) is None
    monkeypatch.delenv("HDS_PROGRAM_CACHE")

    class Opaque:  # neither a dataclass nor a container: its content is unknown
        pass

    opaque = Opaque()
    with pytest.raises(Unhashable, match="Opaque"):
        fingerprint(lambda x: (x, opaque))
    assert program_key(cfg, lambda x: (x, opaque)) is None


def test_a_changed_global_of_a_function_outside_hds_changes_its_fingerprint(tmp_path):
    """A user's module-level constant, edited between two runs, is read by the function as a
    global: its bytecode is the same, its program is not."""
    import importlib.util

    def load(text: str):
        path = tmp_path / "user_effect.py"
        path.write_text(text)
        spec = importlib.util.spec_from_file_location("user_effect", path)
        module = importlib.util.module_from_spec(spec)
        sys.modules["user_effect"] = module
        spec.loader.exec_module(module)
        return module.force

    try:
        first = fingerprint(load("GAIN = 2.0\ndef force(v):\n    return -GAIN * v\n"))
        again = fingerprint(load("GAIN = 2.0\ndef force(v):\n    return -GAIN * v\n"))
        edited = fingerprint(load("GAIN = 3.0\ndef force(v):\n    return -GAIN * v\n"))
    finally:
        sys.modules.pop("user_effect", None)
    assert first == again
    assert first != edited
