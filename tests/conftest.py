"""Shared fixtures. JAX compiles are the main cost on CPU: build each env and compile each
function once per session (session-scoped fixtures), with the persistent compilation cache on.

Writing a cheap test (`make test` must stay under 10 minutes on 2 cores from an empty cache):
- Train on one of the shared budgets below, `TINY` (runs, shapes and bookkeeping) or `FAST`
  (a policy that learns), plus only the overrides the test is about. Every file that trains
  with the same shapes lowers the same programs, so the persistent compilation cache (shared
  by both workers and every `python -m hds.run` the tests start) compiles them once for the
  whole suite; a budget of its own (another rollout count, horizon, chunk or evaluation
  episodes) compiles every program again. Seeds, swept values and `algo.epochs` do not split
  programs, except where the epochs change the chunk (their largest divisor not above
  `algo.chunk`).
- Build what several tests read once: a module- or session-scoped fixture, not a training
  per test.
- A learned dynamics model or a discovery in a test that checks something else: the
  smallest data and fitting budget (`dynamics.episodes`, `dynamics.horizon`,
  `dynamics.epochs`), as the defaults fit for minutes.
- A test over ~20 s goes under `@pytest.mark.slow`, with a cheaper test of the same
  behaviour left in `make test`."""

from __future__ import annotations

import os
import runpy
import struct
import warnings
from pathlib import Path

# The tests' budgets are tiny, so XLA's compiles are most of their time; LLVM at -O1 compiles
# about a third faster than the default -O2 (-O0 compiles faster still but runs slower: the
# whole suite took no less, 2-core AMD EPYC, 2026-11-27). Its floating point is not bitwise
# -O2's (a tiny run
# prints the same table; a full `make run` trains to other numbers, as training amplifies any
# rounding difference), so every number a test compares comes from this session's flags: set
# before JAX starts its backend, and the runs the tests start inherit it.
# XLA's newer CPU fusion emitters (on by default in jax 0.9) compile slower than its classic ones:
# a FAST trainer chunk in 6.6-7.7 CPU s without them against 10.4-13.1 s with (two runs each,
# 2-core AMD EPYC at load 7-10, 2026-11-27), and its run took no longer; its return differs in
# the 7th digit, so as with -O1 every number a test compares comes from this session's flags.
for flag in ("--xla_backend_optimization_level=1", "--xla_cpu_use_fusion_emitters=false"):
    if flag.split("=")[0] not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + flag).strip()
# The program cache (hds.utils.runtime.program_key) serves a second process of a configuration;
# most programs of the suite are traced once, where a miss also serializes the program and
# lowers it again, so the suite (and the runs it starts) keeps it off, its cold time measured
# without it; tests/test_program_cache.py turns it on for its own tests.
os.environ.setdefault("HDS_PROGRAM_CACHE", "off")
os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")

# hds first: it quiets XLA's C++ log before jax loads, as in the runs
import hds  # noqa: E402, F401

# isort: split
import jax  # noqa: E402
import pytest  # noqa: E402

from hds.config import compose  # noqa: E402
from hds.utils.runtime import enable_compilation_cache  # noqa: E402

enable_compilation_cache()
# This process compiles thousands of small eager programs no later process reuses; writing each
# to the cache cost the cold suite time (13 min 0 s against 12 min 16 s, one run each). The
# runs the tests start (hds.run, python -m ...) keep every program, as users' runs do.
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "hds" / "conf"
SHARED = ROOT.parent / "shared"


# make test runs on two workers, a file each at a time (--dist loadfile), in collection order
# (--no-loadscope-reorder: xdist would put the files with most tests first). Every file is ranked
# by its cost, longest first, so the workers finish together: a worker takes the next file when
# it has two tests left, and a long file taken late leaves the other worker idle at the end.
# Cost: CPU s of the file alone from an empty cache (2-core AMD EPYC, loaded, 2026-11-28, sixth
# pass; test_breakaway seventh; test_api eighth, its 100 scaled by its cut, 71.4 -> 55.6 CPU s:
# experiments/test_suite_time/README.md): discover 173, sweeps 134, dynamics 92, api 78,
# train 78, robustness 51, tree 49, envs 46, config 44, design 40, lab 38,
# analytic 37, plants 37, program_cache 35, loop 34, improve 30, cli 25, data 20, regress 16,
# lab_study 14, effects 13, multiarm 13, bench 12, install 10, sysid 10, breakaway 9,
# pictures 8, story 7, dr 7, optuna 7, simulators 6, layers 6; the rest below 6. A new file not
# listed runs after these: add it where its cost puts it.
LONGEST_FIRST = (
    "test_discover.py",
    "test_sweeps.py",
    "test_dynamics.py",
    "test_api.py",
    "test_train.py",
    "test_robustness.py",
    "test_tree.py",
    "test_envs.py",
    "test_config.py",
    "test_design.py",
    "test_lab.py",
    "test_analytic.py",
    "test_plants.py",
    "test_program_cache.py",
    "test_loop.py",
    "test_improve.py",
    "test_cli.py",
    "test_data.py",
    "test_regress.py",
    "test_lab_study.py",
    "test_effects.py",
    "test_multiarm.py",
    "test_bench.py",
    "test_install.py",
    "test_sysid.py",
    "test_breakaway.py",
    "test_pictures.py",
    "test_story.py",
    "test_dr.py",
    "test_optuna.py",
    "test_simulators.py",
    "test_layers.py",
    "test_continuation.py",
    "test_results.py",
    "test_docs.py",
)


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: rest as collected


# The tests' shared budgets on the closed-form engine (compiles in seconds; tests/test_analytic.py
# checks it against brax and MuJoCo). TINY: 4 rollouts of 10 steps, one regression epoch: for
# what runs, not for what it learns. FAST: conf/debug/fast.yaml (16 rollouts of 30 steps, 6
# epochs in chunks of 3), where a test needs the policy to improve.
TINY = (
    "env.backend=analytic",
    "algo.epochs=2",
    "algo.chunk=2",
    "algo.rollouts=4",
    "env.task.horizon=10",
    "algo.inner_epochs=1",
    "eval_episodes=2",
    "logger=none",
)
FAST = ("debug=fast", "logger=none")


def make_config(*overrides: str, config_name: str = "config"):
    """Compose a primary config (conf/config.yaml: `python -m hds.run`; conf/discover.yaml:
    `python -m hds.discover`) with overrides and validate it, as the command does."""
    return compose(list(overrides), config_name)


def command_main(module: str):
    """A command's main(argv), without importing its module under its name: `import
    hds.evaluate` would make the package's attribute `hds.evaluate` that module, hiding the
    deprecated alias of hds.evaluate_policy for the rest of the session (as `import hds.export`).
    runpy warns where another test imported the module already: this run is a fresh copy of
    it, which is the point, so the warning says nothing here."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "'hds[.a-z_]*' found in sys.modules", RuntimeWarning)
        return runpy.run_module(module)["main"]


def trained(*args, **kwargs):
    """(params, history) of hds.experiment.train_batch(*args, **kwargs)."""
    from hds.experiment import train_batch

    training = train_batch(*args, **kwargs)
    return training.params, training.history


def train_in_chunks(cfg, trainer):
    """(state, metrics [runs, epochs]) of the runs of cfg, trained by `trainer` as
    hds.experiment.train trains them: init, then run_chunk over the chunks of epochs, with its
    compiled programs (on a CPU one run's, run by run). On a shared budget those are the
    programs of every other training of these shapes in the suite (the persistent cache's),
    where a jit of the whole training (`jax.jit(trainer.train)`) compiles a program of its own."""
    import numpy as np

    from hds.experiment import batch_hparams, compiled_programs

    init, run_chunk, keys, hparams = compiled_programs(cfg, trainer, batch_hparams(cfg, trainer))
    state, chunks = init(keys, hparams), []
    for _ in range(cfg.algo.epochs // trainer.chunk):
        state, metrics = run_chunk(state, hparams)
        chunks.append(metrics)
    return state, jax.tree.map(lambda *m: np.concatenate(m, axis=1), *chunks)


def wandb_records(run_dir: Path) -> dict[str, list]:
    """Every record of every offline W&B run below run_dir ({run directory name: records}),
    read back from its `run-<id>.wandb` file: protobuf records in leveldb's log format (32 KiB
    blocks after a 7-byte `:W&B` header; each chunk: crc32, length, type 1 full / 2 first /
    3 middle / 4 last)."""
    from wandb.proto.wandb_internal_pb2 import Record

    out = {}
    for path in sorted(Path(run_dir).glob("wandb/offline-run-*/run-*.wandb")):
        data, records = path.read_bytes(), []
        assert data[:4] == b":W&B", path
        pos, chunks = 7, b""
        while pos + 7 <= len(data):
            if 32768 - pos % 32768 < 7:  # a block's trailer
                pos += 32768 - pos % 32768
                continue
            _, length, kind = struct.unpack("<IHB", data[pos : pos + 7])
            chunks += data[pos + 7 : pos + 7 + length]
            pos += 7 + length
            if kind in (1, 4):
                records.append(Record.FromString(chunks))
                chunks = b""
        out[path.parent.name] = records
    return out


def wandb_keys(records, field: str) -> dict[str, str]:
    """{key: value_json} of the history rows (field="history") or summary updates ("summary")
    of W&B records; nested keys joined by "/" (W&B splits keys that hold one)."""
    items = [
        i
        for r in records
        if r.HasField(field)
        for i in (r.history.item if field == "history" else r.summary.update)
    ]
    return {i.key or "/".join(i.nested_key): i.value_json for i in items}


@pytest.fixture(scope="session")
def cartpole_cfg():
    return make_config().env


@pytest.fixture(scope="session")
def cartpole_env(cartpole_cfg):
    from hds.envs import make_env

    return make_env(cartpole_cfg)
