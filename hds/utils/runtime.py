"""Process-wide JAX set-up: the persistent compilation cache (a second process skips compiling)."""

from __future__ import annotations

import os
from pathlib import Path

import jax
import numpy as np

DEFAULT_CACHE = Path(os.environ.get("HDS_JAX_CACHE", Path.home() / ".cache" / "hds" / "jax"))


def enable_compilation_cache(path: str | Path | None = None) -> Path:
    """Turn on JAX's persistent compilation cache at `path` (default: $HDS_JAX_CACHE or
    ~/.cache/hds/jax). Without a path, a cache this process already set up is kept as it is
    (its settings included)."""
    configured = jax.config.jax_compilation_cache_dir
    if path is None and configured:
        return Path(configured)
    path = Path(path or DEFAULT_CACHE).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    # every program, however small: a run compiles ~150 small ones (eager ops, helpers) of
    # 0.01-0.5 s, ~9 s in all, which a cached read makes ~10 s less CPU for each later process
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def runs_vmapped(setting: int | None, runs: int) -> int:
    """How many runs of a batch one program vmaps at a time. `None` (auto): all of them where the
    batch is sharded across several devices or runs on an accelerator; one on a single CPU,
    where a vmapped epoch costs more than its runs one after another (a batched `lax.cond`
    runs both branches, batched matmuls and gathers are slower) and where a run's numbers
    should not depend on how many ran beside it. 0: all of them."""
    if setting is None:
        one_cpu = jax.default_backend() == "cpu" and jax.device_count() == 1
        return 1 if one_cpu else runs
    return runs if setting == 0 else min(setting, runs)


def over_runs(fn, vmapped: int, runs: int):
    """`fn` mapped over the leading axis of its arguments (a batch of `runs` runs), `vmapped` at
    a time in one compiled program: a `jax.lax.map` loop over single runs (never a vmap of one),
    `jax.vmap` over all of them, or a loop over vmapped groups."""
    if vmapped == 1:  # lax.map's batch_size would vmap groups of one
        return lambda *args: jax.lax.map(lambda a: fn(*a), args)
    if vmapped >= runs:
        return jax.vmap(fn)
    return lambda *args: jax.lax.map(lambda a: fn(*a), args, batch_size=vmapped)


class RunByRun:
    """`fn` of one run, jitted once and called on each run of a batch (the leading axis of
    every argument) in a host loop, the results stacked: how a single CPU trains a batch
    (`runs_vmapped` 1). The program has one run's shapes, so every batch of runs of one
    configuration (1 seed or 5, a sweep of step sizes or friction gaps, a plant's draw) and
    every later process shares one compile and one persistent-cache entry, where a `lax.map`
    over the batch compiled a program per batch size. Each run's numbers are bit for bit those
    of the `lax.map` (the same loop body). `lower(*args).compile()` mirrors `jax.jit`'s AOT API."""

    def __init__(self, fn, compiled=None):
        self.fn = fn
        self.program = compiled if compiled is not None else jax.jit(fn)

    def __call__(self, *args):
        host = jax.tree.map(np.asarray, args)  # one run's slice is a view, not an eager op
        runs = jax.tree.leaves(host)[0].shape[0]
        outs = [self.program(*jax.tree.map(lambda x, i=i: x[i], host)) for i in range(runs)]
        return jax.tree.map(lambda *xs: jax.device_put(np.stack(xs)), *outs)

    def lower(self, *args):
        first = jax.tree.map(lambda x: np.asarray(x)[0], args)
        return _LoweredRuns(self.fn, self.program.lower(*first))


class _LoweredRuns:
    def __init__(self, fn, lowered):
        self.fn, self.lowered = fn, lowered

    def compile(self) -> RunByRun:
        return RunByRun(self.fn, self.lowered.compile())
