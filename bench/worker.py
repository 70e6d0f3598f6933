"""`python -m bench.worker KIND SPEC_JSON OUT_JSON`: one measurement in a fresh process, so that
compile caches are cold (or warm from disk only), and peak memory is this measurement's own.

KIND `train`: compose the config of SPEC["overrides"], build the env and trainer, trace and
compile, optionally run, and write timings, XLA's memory analysis and peak RSS to OUT_JSON.
  SPEC["program"]  "train": trainer.train over SPEC["seeds"] seeds (the whole run as one
                   program); "chunk": what hds.run compiles, trainer.run_chunk over the seeds
                   after a jitted init; both jitted, mapped over the seeds as hds.run maps them
                   (hds.utils.runtime.over_runs)
  SPEC["vmapped"]  how many seeds are vmapped at a time, as hds.run's `vmap_runs` (default
                   null: what hds.run does here; 0: all; 1: a loop over them)
  SPEC["run"]      run the compiled program (default true): a first call (`first_run_s`, which
                   also pays first-call allocations), then up to SPEC["repeats"] more (default
                   0) while they take less than SPEC["repeat_s"] seconds in all (default 30);
                   `run_s` is their median, or the first call's time where there are none
  SPEC["cache"]    a persistent compilation cache directory (default: none, a cold compile)
"""

from __future__ import annotations

import time

_START = time.perf_counter()

import json  # noqa: E402
import sys  # noqa: E402

from bench.common import best_of, block, compose, peak_rss_mb, timed  # noqa: E402
from hds.utils.runtime import over_runs, runs_vmapped  # noqa: E402


def memory_analysis(compiled) -> dict | None:
    """XLA's static memory plan of a compiled program, in MiB (None where unsupported)."""
    try:
        stats = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - not every backend implements it
        return None
    if stats is None:
        return None
    fields = (
        "temp_size_in_bytes",
        "argument_size_in_bytes",
        "output_size_in_bytes",
        "generated_code_size_in_bytes",
    )
    return {
        f.replace("_size_in_bytes", "_mib"): getattr(stats, f) / 2**20
        for f in fields
        if hasattr(stats, f)
    }


def train(spec: dict) -> dict:
    import jax
    import jax.numpy as jnp

    if spec.get("cache"):
        from hds.utils.runtime import enable_compilation_cache

        enable_compilation_cache(spec["cache"])
    from hds.algo.pods import make_train_from_config
    from hds.envs import make_env

    import_s = time.perf_counter() - _START
    with timed() as build:
        cfg = compose(*spec["overrides"])
        env = make_env(cfg.env)
        trainer = make_train_from_config(cfg, env)
    rss_built = peak_rss_mb()
    seeds = int(spec.get("seeds", 1))
    keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(seeds))
    hparams = jax.tree.map(lambda x: jnp.stack([x] * seeds), trainer.default_hparams)
    vmapped = runs_vmapped(spec.get("vmapped"), seeds)
    out = {
        "import_s": import_s,
        "build_s": build.s,
        "rss_after_build_mb": rss_built,
        "seeds": seeds,
        "vmapped": vmapped,
        "epochs": cfg.algo.epochs,
    }
    if spec.get("program", "train") == "chunk":
        with timed() as init_t:
            state = block(jax.jit(over_runs(trainer.init, vmapped, seeds))(keys, hparams))
        fn, args = jax.jit(over_runs(trainer.run_chunk, vmapped, seeds)), (state, hparams)
        out.update(init_s=init_t.s, epochs_per_call=trainer.chunk)
    else:
        fn, args = jax.jit(over_runs(trainer.train, vmapped, seeds)), (keys, hparams)
    with timed() as trace:
        lowered = fn.lower(*args)
    with timed() as comp:
        compiled = lowered.compile()
    out.update(trace_s=trace.s, compile_s=comp.s, memory=memory_analysis(compiled))
    if spec.get("run", True):
        out.update(run_calls(lambda: block(compiled(*args)), spec))
    out["peak_rss_mb"] = peak_rss_mb()
    out["worker_s"] = time.perf_counter() - _START
    return out


def run_calls(call, spec: dict) -> dict:
    with timed() as first:
        call()
    fit = int(spec.get("repeat_s", 30.0) // max(first.s, 1e-9))  # judged by the first call
    repeats = min(int(spec.get("repeats", 0)), fit)
    median, times = best_of(call, repeats) if repeats > 0 else (first.s, [])
    return {"first_run_s": first.s, "run_s": median, "repeat_run_s": times}


KINDS = {"train": train}


def main() -> None:
    kind, spec, path = sys.argv[1], json.loads(sys.argv[2]), sys.argv[3]
    result = KINDS[kind](spec)
    with open(path, "w") as f:
        json.dump(result, f)


if __name__ == "__main__":
    main()
