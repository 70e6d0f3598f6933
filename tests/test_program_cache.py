"""The program cache (hds.utils.runtime): the trainer's lowered program kept across processes
by jax.export, under a key of everything it is built from."""

from __future__ import annotations

import os
import sys

import jax
import numpy as np
import pytest

from hds.envs import analytic, make_env
from hds.experiment import batch_hparams, compiled_programs, trainer_program_key
from hds.utils import runtime
from hds.utils.runtime import RunByRun, Unhashable, fingerprint, program_key
from tests.conftest import ROOT, TINY, make_config


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


@pytest.mark.parametrize("cached", [False, True])
def test_init_run_beside_the_chunk_s_compile_gives_the_numbers_of_one_after_the_other(
    cached, tiny, tmp_path, monkeypatch
):
    """start_and_compile (init compiled and run on a second thread, the chunk lowered from
    init's output shapes): the state and a chunk's outputs of init called, then the chunk
    lowered on its state, to the last digit; a prepared state of other shapes gets its own
    chunk."""
    cfg, trainer = tiny
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path) if cached else "off")
    hparams = batch_hparams(cfg, trainer)
    init, chunk, keys, hparams = compiled_programs(cfg, trainer, hparams)
    assert isinstance(init, RunByRun)
    before = init(keys, hparams)
    expected = jax.tree.leaves(chunk.lower(before, hparams).compile()(before, hparams))
    init, chunk, keys, hparams = compiled_programs(cfg, trainer, hparams)
    timing = {}
    state, compiled = runtime.start_and_compile(init, chunk, keys, hparams, timing=timing)
    assert set(timing) == {"init_s", "trace_s", "compile_s"}
    for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(state), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for a, b in zip(expected, jax.tree.leaves(compiled(state, hparams)), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))

    lowered = []  # (the state's per-run epoch shape) of each lowering of the chunk
    real = chunk.lower

    class Program:
        def compile(self):
            return "its own program"

    def spy(state, hparams):
        lowered.append(state.epoch.shape[1:])
        return real(state, hparams) if len(lowered) == 1 else Program()

    def wider(s):  # another shape than init's: the chunk lowered from init's would refuse it
        return s.replace(epoch=jax.numpy.stack([s.epoch, s.epoch], axis=1))

    monkeypatch.setattr(chunk, "lower", spy)
    prepared, program = runtime.start_and_compile(init, chunk, keys, hparams, wider)
    assert lowered == [(), (2,)] and program == "its own program"


# XLA's own settings, whatever the session's XLA_FLAGS (tests/conftest.py sets RUN_ONCE's)
XLA_DEFAULTS = {"xla_backend_optimization_level": 3, "xla_cpu_use_fusion_emitters": True}


@pytest.mark.parametrize(
    "overrides",
    [TINY, ("env=double_cartpole_balance", "real.effects=[]", "algo.rollouts=4", "logger=none")],
    ids=["cartpole-analytic", "double-cartpole-tree"],
)
def test_init_compiled_at_run_once_gives_the_numbers_of_xla_s_defaults(overrides):
    """start_and_compile compiles init at RUN_ONCE (cheaper, same numbers): every leaf of the
    state equals that of init compiled at XLA's defaults, to the last bit, on five seeds."""
    from hds.algo.pods import make_train_from_config

    cfg = make_config(*overrides)
    trainer = make_train_from_config(cfg, make_env(cfg.env))
    lowered = jax.jit(trainer.init).lower(jax.random.PRNGKey(0), trainer.default_hparams)
    once, default = lowered.compile(runtime.RUN_ONCE), lowered.compile(XLA_DEFAULTS)
    assert once.as_text() != default.as_text()  # two compilations, not one program twice
    for seed in range(5):
        key = jax.random.PRNGKey(seed)
        a = jax.tree.leaves(once(key, trainer.default_hparams))
        b = jax.tree.leaves(default(key, trainer.default_hparams))
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


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
    # init's and the chunk's serialized programs, each with its output structure
    assert len(entries) == 4

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


def test_init_from_the_program_cache_gives_the_numbers_of_jit_to_the_last_digit(
    tiny, tmp_path, monkeypatch
):
    cfg, trainer = tiny
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    hparams = batch_hparams(cfg, trainer)
    _, _, keys, hparams = compiled_programs(cfg, trainer, hparams)
    key = program_key(cfg, trainer.init)
    assert key is not None and key != program_key(cfg, trainer.run_chunk)
    plain = RunByRun(trainer.init)(keys, hparams)  # no key: jax.jit
    miss = RunByRun(trainer.init, key=key)(keys, hparams)
    assert len(list(tmp_path.glob("*.jaxexport"))) == 1

    def never(*args):  # a hit deserializes init's program: it is not traced
        raise AssertionError("traced on a hit")

    hit = RunByRun(never, key=key)(keys, hparams)
    for a, b, c in zip(*map(jax.tree.leaves, (plain, miss, hit)), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(b), np.asarray(c))


def test_a_programs_entry_is_keyed_by_the_dtypes_jax_sees(tmp_path):
    """cached_lowering reads each argument's dtype as jax will see it, without converting it:
    a float64 array and a Python int (float32 and int32 to jax) share the entry of float32 and
    int32 arrays, with the same numbers; another dtype is another entry."""
    from hds.utils.runtime import cached_lowering

    def fn(x, n):
        return x * n + 1.0

    as_numpy = (np.arange(4, dtype=np.float64), 3)
    as_jax = (jax.numpy.arange(4, dtype=jax.numpy.float32), jax.numpy.int32(3))
    first = cached_lowering(fn, as_numpy, "k", tmp_path).compile()(*as_numpy)
    entries = sorted(tmp_path.iterdir())
    again = cached_lowering(fn, as_jax, "k", tmp_path).compile()(*as_jax)
    assert sorted(tmp_path.iterdir()) == entries
    np.testing.assert_array_equal(np.asarray(first), np.asarray(again))
    cached_lowering(fn, (np.arange(4, dtype=np.int32), 3), "k", tmp_path)
    assert len(list(tmp_path.iterdir())) == len(entries) + 2  # a new program and its tree


# --- brax's System (hds.envs.system.brax_system), kept by cached_build ------------------------
def build_counted(monkeypatch, **kwargs):
    """make_simulator's System and how many times brax's load_model built one."""
    from brax.io import mjcf

    from hds.envs.system import make_simulator

    calls = []
    real = mjcf.load_model
    monkeypatch.setattr(mjcf, "load_model", lambda m: calls.append(m) or real(m))
    sim, _ = make_simulator("cartpole.xml", backend="generalized", **kwargs)
    sys = sim.sys  # built (or read) on first use: hds.envs.system.LazySystem
    monkeypatch.setattr(mjcf, "load_model", real)
    return sys, len(calls)


def assert_same_system(a, b):
    leaves_a, leaves_b = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(leaves_a) == len(leaves_b)
    for x, y in zip(leaves_a, leaves_b, strict=True):
        assert type(x) is type(y) and x.dtype == y.dtype
        assert getattr(x, "weak_type", None) == getattr(y, "weak_type", None)
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # every field, static ones and the MuJoCo model's binary included
    assert fingerprint(a) == fingerprint(b)


def test_a_cached_brax_system_is_the_built_one_to_the_last_digit(tmp_path, monkeypatch):
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    built, calls = build_counted(monkeypatch)
    assert calls == 1 and len(list(tmp_path.glob("*.brax_system.pickle"))) == 1
    hit, calls = build_counted(monkeypatch)
    assert calls == 0  # unpickled, not built
    assert_same_system(built, hit)
    monkeypatch.setenv("HDS_PROGRAM_CACHE", "off")
    plain, calls = build_counted(monkeypatch)
    assert calls == 1 and len(list(tmp_path.glob("*.brax_system.pickle"))) == 1
    assert_same_system(plain, hit)


def test_a_changed_model_or_source_file_misses_the_system_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    build_counted(monkeypatch)
    other, calls = build_counted(monkeypatch, timestep=0.005)  # another MuJoCo model
    assert calls == 1 and np.float32(other.opt.timestep) == np.float32(0.005)
    monkeypatch.setattr(runtime, "source_digest", lambda: "an edited source file")
    _, calls = build_counted(monkeypatch)
    assert calls == 1
    assert len(list(tmp_path.glob("*.brax_system.pickle"))) == 3


def test_a_corrupt_system_cache_entry_is_built_again_not_a_crash(tmp_path, monkeypatch):
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    built, _ = build_counted(monkeypatch)
    (entry,) = tmp_path.glob("*.brax_system.pickle")
    entry.write_bytes(entry.read_bytes()[:100])  # cut short, as a full disk might leave it
    again, calls = build_counted(monkeypatch)
    assert calls == 1
    assert_same_system(built, again)
    hit, calls = build_counted(monkeypatch)  # rewritten whole
    assert calls == 0
    assert_same_system(built, hit)


def test_the_trainer_key_ignores_the_logger_and_nothing_that_changes_a_result(
    tiny, tmp_path, monkeypatch
):
    """make run names each sweep's W&B group after its new directory: a second make run
    must find the first one's programs; a setting that changes the program must not."""
    cfg, trainer = tiny
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    key = trainer_program_key(cfg, trainer.run_chunk)
    assert key is not None
    grouped = make_config(*TINY, "logger.group=multiruns/another/2026-11-27_22-30-00")
    assert trainer_program_key(grouped, trainer.run_chunk) == key
    threaded = make_config(*TINY, "threads=1", "discover.threads=1")
    assert trainer_program_key(threaded, trainer.run_chunk) == key
    other = make_config(*TINY, "algo.learning_rate=2e-3")
    assert trainer_program_key(other, trainer.run_chunk) != key
    assert trainer_program_key(cfg, trainer.init) != key


# --- the System on first use (hds.envs.system.LazySystem): a warm process needs no brax --------
def test_a_checked_model_builds_no_system_until_used_and_keeps_its_key(tmp_path, monkeypatch):
    from hds.envs import system

    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    first, _ = system.make_simulator("cartpole.xml", backend="analytic")
    key = fingerprint(first)  # the System was built for the backend's check
    assert len(list(tmp_path.glob("*.backend_check.pickle"))) == 1

    def never(model):
        raise AssertionError("the System was built or read")

    built = system.brax_system
    monkeypatch.setattr(system, "brax_system", never)
    warm, _ = system.make_simulator("cartpole.xml", backend="analytic")  # the check: a hit
    assert fingerprint(warm) == key  # the same program key as the process that built it
    monkeypatch.setattr(system, "brax_system", built)
    assert_same_system(warm.sys, first.sys)  # built on first use, to the last digit
    assert fingerprint(warm) == key  # building it does not change its content
    other, _ = system.make_simulator("cartpole.xml", backend="tree")  # another key: checked
    assert fingerprint(other) != key
    assert len(list(tmp_path.glob("*.backend_check.pickle"))) == 2


def test_a_corrupt_backend_check_is_run_again_and_a_refusal_is_never_kept(tmp_path, monkeypatch):
    from hds.envs import system

    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    system.make_simulator("cartpole.xml", backend="analytic")
    (entry,) = tmp_path.glob("*.backend_check.pickle")
    entry.write_bytes(b"\x80")  # cut short
    checks = []
    monkeypatch.setattr(analytic, "check", lambda sys: checks.append(sys) or "cartpole")
    system.make_simulator("cartpole.xml", backend="analytic")
    assert len(checks) == 1  # run again on the built System, and rewritten
    system.make_simulator("cartpole.xml", backend="analytic")
    assert len(checks) == 1

    def refuse(sys):
        raise ValueError("unsupported")

    monkeypatch.setattr(analytic, "check", refuse)
    for _ in range(2):  # another model: refused each time, nothing kept
        with pytest.raises(ValueError, match="unsupported"):
            system.make_simulator("cartpole.xml", backend="analytic", timestep=0.005)
    assert len(list(tmp_path.glob("*.backend_check.pickle"))) == 1


def test_no_process_of_an_own_backend_imports_brax(tmp_path):
    """What it saves (~1 s): brax imports mujoco.mjx, trimesh and scipy.spatial. The first
    process builds the System without brax (hds.envs.mjsystem) and checks the model; the
    second reads the check from the program cache."""
    import subprocess

    script = (
        "import sys; from hds.envs import make_env; from hds.utils.runtime import fingerprint;"
        "from hds.config.composition import compose;"
        "env = make_env(compose(['env.backend=analytic']).env);"
        "print(fingerprint(env), 'brax' in sys.modules, 'mujoco.mjx' in sys.modules)"
    )
    env = {**os.environ, "HDS_PROGRAM_CACHE": str(tmp_path)}
    runs = [
        subprocess.run(
            [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True
        ).stdout.split()[-3:]
        for _ in range(2)
    ]
    assert runs[0][1:] == ["False", "False"]  # the first built (and checked) it
    assert runs[1] == [runs[0][0], "False", "False"]


def test_a_second_process_of_a_trainer_imports_neither_flax_nor_glfw(tmp_path):
    """A process whose trainer's init comes from the program cache never calls the policy's
    flax module (hds.networks.Policy makes it on first use), and a command imports MuJoCo
    without its in-process OpenGL (hds.utils.runtime.headless_mujoco), leaving MUJOCO_GL as
    it was; the second process's init gives the first one's numbers."""
    import subprocess

    from tests.conftest import TINY

    script = (
        "import os, sys; from hds.utils.runtime import headless_mujoco; headless_mujoco();"
        "import numpy as np; from hds.config import compose; from hds.envs import make_env;"
        "from hds.algo.pods import make_train_from_config;"
        "from hds.experiment import batch_hparams, compiled_programs;"
        f"cfg = compose({list(TINY)!r}); trainer = make_train_from_config(cfg, make_env(cfg.env));"
        "init, _, keys, hparams = compiled_programs(cfg, trainer, batch_hparams(cfg, trainer));"
        "state = init(keys, hparams);"
        "print(float(np.sum(state.policy['params']['Dense_0']['kernel'])),"
        "'flax' in sys.modules, 'glfw' in sys.modules, 'MUJOCO_GL' in os.environ)"
    )
    env = {k: v for k, v in os.environ.items() if k != "MUJOCO_GL"}
    env["HDS_PROGRAM_CACHE"] = str(tmp_path)
    runs = [
        subprocess.run(
            [sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True
        ).stdout.split()[-4:]
        for _ in range(2)
    ]
    assert runs[0][1:] == ["True", "False", "False"]  # the first traced init: flax it needs
    assert runs[1] == [runs[0][0], "False", "False", "False"]


@pytest.mark.parametrize("backend", ["analytic", "generalized"])
def test_a_system_first_used_inside_a_trace_is_built_with_concrete_arrays(
    backend, tmp_path, monkeypatch
):
    """Discovery's fit reads the System while jit traces it: it is built eagerly all the same
    (brax's kept in the cache, the numbers of an eager build), never as the trace's values."""
    from hds.envs import system

    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    eager, _ = system.make_simulator("cartpole.xml", backend=backend)
    eager.sys  # noqa: B018 - built
    for entry in tmp_path.glob("*.brax_system.pickle"):
        entry.unlink()  # the check is kept: the next simulator builds its System on first use
    lazy, _ = system.make_simulator("cartpole.xml", backend=backend)
    damping = jax.jit(lambda x: x * lazy.sys.dof.damping)(np.float32(2.0))
    assert not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(lazy.sys))
    assert_same_system(lazy.sys, eager.sys)
    np.testing.assert_array_equal(damping, 2.0 * np.asarray(eager.sys.dof.damping))
    kept = 1 if backend == "generalized" else 0  # the own backends' System is not pickled
    assert len(list(tmp_path.glob("*.brax_system.pickle"))) == kept


# --- the composed config (hds.config.composition): a second process skips Hydra's compose ------
def compose_counted(monkeypatch, *overrides, config_dirs=()):
    from hds.config import composition

    calls = []
    real = composition._compose_now

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(composition, "_compose_now", counted)
    return composition.compose(list(overrides), config_dirs=config_dirs), len(calls)


def test_a_cached_composition_is_the_composed_config(tmp_path, monkeypatch):
    from omegaconf import OmegaConf

    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    built, calls = compose_counted(monkeypatch, "env.backend=analytic", "seeds=2")
    assert calls == 1 and len(list(tmp_path.glob("*.composed_config.pickle"))) == 1
    hit, calls = compose_counted(monkeypatch, "env.backend=analytic", "seeds=2")
    assert calls == 0  # unpickled, not composed
    assert OmegaConf.to_yaml(OmegaConf.structured(hit)) == OmegaConf.to_yaml(
        OmegaConf.structured(built)
    )
    assert hit == built and hit.seeds == 2
    monkeypatch.setenv("HDS_PROGRAM_CACHE", "off")
    plain, calls = compose_counted(monkeypatch, "env.backend=analytic", "seeds=2")
    assert calls == 1 and plain == hit


def test_an_override_a_config_file_or_the_config_store_misses_the_composition(
    tmp_path, monkeypatch
):
    from hydra.core.config_store import ConfigStore

    cache, study = tmp_path / "cache", tmp_path / "study"
    (study / "algo").mkdir(parents=True)
    algo = study / "algo" / "mine.yaml"
    algo.write_text("defaults:\n  - pods\n  - _self_\nepochs: 7\n")
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(cache))
    cfg, calls = compose_counted(monkeypatch, "algo=mine", config_dirs=[study])
    assert calls == 1 and cfg.algo.epochs == 7
    cfg, calls = compose_counted(monkeypatch, "algo=mine", config_dirs=[study])
    assert calls == 0 and cfg.algo.epochs == 7
    algo.write_text("defaults:\n  - pods\n  - _self_\nepochs: 9\n")  # the study's file edited
    cfg, calls = compose_counted(monkeypatch, "algo=mine", config_dirs=[study])
    assert calls == 1 and cfg.algo.epochs == 9
    cfg, calls = compose_counted(monkeypatch, "algo=mine", "seeds=3", config_dirs=[study])
    assert calls == 1 and cfg.seeds == 3 and cfg.algo.epochs == 9
    before = len(list(cache.glob("*.composed_config.pickle")))
    ConfigStore.instance().store(group="algo", name="stored_here", node={"epochs": 5})
    try:  # an entry stored in this process: the store's content is in the key
        _, calls = compose_counted(monkeypatch, "algo=mine", config_dirs=[study])
        assert calls == 1
        assert len(list(cache.glob("*.composed_config.pickle"))) == before + 1
    finally:
        del ConfigStore.instance().repo["algo"]["stored_here.yaml"]
    monkeypatch.setattr(runtime, "source_digest", lambda: "an edited hds/conf file")
    _, calls = compose_counted(monkeypatch, "algo=mine", config_dirs=[study])
    assert calls == 1


def test_a_corrupt_composition_entry_is_composed_again_not_a_crash(tmp_path, monkeypatch):
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    built, _ = compose_counted(monkeypatch, "seeds=2")
    (entry,) = tmp_path.glob("*.composed_config.pickle")
    entry.write_bytes(entry.read_bytes()[:100])  # cut short, as a full disk might leave it
    again, calls = compose_counted(monkeypatch, "seeds=2")
    assert calls == 1 and again == built
    hit, calls = compose_counted(monkeypatch, "seeds=2")  # rewritten whole
    assert calls == 0 and hit == built


# --- the evaluation after training (hds.gap.Evaluator): from the program cache like the chunk ---
def evaluation(monkeypatch, tiny, cache, episodes: int = 2, never: bool = False):
    """The tiny trainer's initial policies' returns on the simulator, by a new Evaluator
    (`cache`: the program cache's directory or "off"); `never`: tracing the rollout fails."""
    from hds import gap
    from hds.gap import Evaluator

    cfg, trainer = tiny
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(cache))
    hparams = batch_hparams(cfg, trainer)
    _, _, keys, hparams = compiled_programs(cfg, trainer, hparams)
    state = RunByRun(trainer.init)(keys, hparams)
    evaluator = Evaluator(make_env(cfg.env), trainer.policy, None, episodes)
    if never:

        def traced(*args, **kwargs):
            raise AssertionError("the evaluation was traced on a hit")

        monkeypatch.setattr(gap, "policy_rollout", traced)
    try:
        return evaluator, evaluator.sim_returns(state.policy)
    finally:
        monkeypatch.setattr(gap, "policy_rollout", policy_rollout)


from hds.algo.rollout import policy_rollout  # noqa: E402 - restored after `never`


def test_the_evaluation_from_the_program_cache_gives_the_numbers_of_jit_to_the_last_digit(
    tiny, tmp_path, monkeypatch
):
    _, plain = evaluation(monkeypatch, tiny, "off")
    evaluator, miss = evaluation(monkeypatch, tiny, tmp_path)
    assert evaluator._key is not None
    entries = sorted(p.name for p in tmp_path.iterdir())
    assert len([e for e in entries if e.endswith(".jaxexport")]) == 1
    _, hit = evaluation(monkeypatch, tiny, tmp_path, never=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == entries
    assert plain.shape == (1, 2)
    np.testing.assert_array_equal(plain, miss)
    np.testing.assert_array_equal(miss, hit)


@pytest.mark.slow
def test_other_initial_states_miss_the_evaluation_and_a_corrupt_entry_is_traced_again(
    tiny, tmp_path, monkeypatch
):
    first, two = evaluation(monkeypatch, tiny, tmp_path)
    other, three = evaluation(monkeypatch, tiny, tmp_path, episodes=3)
    assert other._key != first._key and three.shape == (1, 3)
    assert len(list(tmp_path.glob("*.jaxexport"))) == 2
    for entry in tmp_path.glob("*.jaxexport"):
        entry.write_bytes(entry.read_bytes()[:100])  # cut short, as a full disk might leave it
    _, again = evaluation(monkeypatch, tiny, tmp_path)
    np.testing.assert_array_equal(again, two)
    _, hit = evaluation(monkeypatch, tiny, tmp_path, never=True)  # rewritten whole
    np.testing.assert_array_equal(hit, two)


def test_an_unknown_override_is_refused_before_composing_and_never_kept(tmp_path, monkeypatch):
    monkeypatch.setenv("HDS_PROGRAM_CACHE", str(tmp_path))
    with pytest.raises(ValueError, match="has no key 'sedes'"):
        compose_counted(monkeypatch, "sedes=2")
    assert not list(tmp_path.glob("*.composed_config.pickle"))


def test_a_second_process_reads_discovery_s_programs_and_gives_their_numbers(tmp_path):
    """Discovery's programs come from the program cache in a second process: nothing traced
    again, the same report to the last digit. Its fits call LAPACK (getrf and trsm, from
    jnp.linalg.solve), whose kernels jaxlib binds only when it lowers a linear-algebra op; a
    program read from the cache is never lowered, so they are bound first
    (hds.utils.runtime.cached_lowering): unbound, the second process crashed."""
    import subprocess

    script = (
        "import json; from bench.discovery import record; from hds.config import compose;"
        "from hds.discover import discover; from hds.discover.config import DiscoverConfig;"
        "from hds.envs import make_env; from hds.real.mujoco_plant import MujocoPlant;"
        "from hds.utils.runtime import enable_compilation_cache; enable_compilation_cache();"
        "cfg = compose(['env.backend=analytic']);"
        "friction = {'name': 'coulomb_friction', 'target': 'slider', 'params': {'force': 20.0}};"
        "data = record(MujocoPlant(cfg.env, [friction]), make_env(cfg.env).task, 6, 40, 0);"
        "cfg_d = DiscoverConfig(effects=['coulomb_friction'], max_delay=0, stride=2,"
        " initial_state='measured', horizon=5);"
        "r = discover(data, cfg.env, cfg_d);"
        "print(json.dumps([[str(e) for e in r.missing_effects], r.candidates], default=str))"
    )
    env = {**os.environ, "HDS_PROGRAM_CACHE": str(tmp_path)}

    def run():
        out = subprocess.run(
            [sys.executable, "-c", script], env=env, cwd=ROOT, capture_output=True, text=True
        )
        assert out.returncode == 0, out.stderr[-2000:]
        return out.stdout.strip().splitlines()[-1]

    first = run()
    entries = sorted(p.name for p in tmp_path.glob("*.jaxexport"))
    assert any(b"lapack_" in (tmp_path / e).read_bytes() for e in entries)
    assert run() == first
    assert sorted(p.name for p in tmp_path.glob("*.jaxexport")) == entries  # all read
    assert "coulomb_friction" in first
