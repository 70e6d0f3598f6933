"""`python -m bench.worker KIND SPEC_JSON OUT_JSON`: one measurement in a fresh process, so that
compile caches are cold (or warm from disk only), and peak memory is this measurement's own.

KIND `train`: compose the config of SPEC["overrides"], build the env and trainer, trace and
compile, optionally run, and write timings, XLA's memory analysis and peak RSS to OUT_JSON.
  SPEC["program"]  "train": jax.jit(jax.vmap(trainer.train)) over SPEC["seeds"] seeds (the whole
                   run as one program); "chunk": what hds.run compiles, jax.jit(jax.vmap(
                   trainer.run_chunk)) after a jitted vmapped init
  SPEC["run"]      run the compiled program once (default true)
  SPEC["cache"]    a persistent compilation cache directory (default: none, a cold compile)
"""

from __future__ import annotations

import time

_START = time.perf_counter()

import json  # noqa: E402
import sys  # noqa: E402

from bench.common import block, compose, peak_rss_mb, timed  # noqa: E402


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
    from hds.algo.pods import make_train
    from hds.envs import make_env

    import_s = time.perf_counter() - _START
    with timed() as build:
        cfg = compose(*spec["overrides"])
        env = make_env(cfg.env)
        trainer = make_train(cfg, env)
    rss_built = peak_rss_mb()
    seeds = int(spec.get("seeds", 1))
    keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(seeds))
    hparams = trainer.default_hparams
    out = {
        "import_s": import_s,
        "build_s": build.s,
        "rss_after_build_mb": rss_built,
        "seeds": seeds,
        "epochs": cfg.algo.epochs,
    }
    if spec.get("program", "train") == "chunk":
        with timed() as init_t:
            state = block(jax.jit(jax.vmap(trainer.init, in_axes=(0, None)))(keys, hparams))
        fn, args = jax.jit(jax.vmap(trainer.run_chunk, in_axes=(0, None))), (state, hparams)
        out.update(init_s=init_t.s, epochs_per_call=trainer.chunk)
    else:
        fn, args = jax.jit(jax.vmap(trainer.train, in_axes=(0, None))), (keys, hparams)
    with timed() as trace:
        lowered = fn.lower(*args)
    with timed() as comp:
        compiled = lowered.compile()
    out.update(trace_s=trace.s, compile_s=comp.s, memory=memory_analysis(compiled))
    if spec.get("run", True):
        with timed() as run:
            block(compiled(*args))
        out["run_s"] = run.s
    out["peak_rss_mb"] = peak_rss_mb()
    out["worker_s"] = time.perf_counter() - _START
    return out


KINDS = {"train": train}


def main() -> None:
    kind, spec, path = sys.argv[1], json.loads(sys.argv[2]), sys.argv[3]
    result = KINDS[kind](spec)
    with open(path, "w") as f:
        json.dump(result, f)


if __name__ == "__main__":
    main()
