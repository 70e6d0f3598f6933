"""`python -m bench.worker KIND SPEC_JSON OUT_JSON`: one measurement in a fresh process, so that
compile caches are cold (or warm from disk only), and peak memory is this measurement's own.

KIND `train`: compose the config of SPEC["overrides"], build the env and trainer, trace and
compile, optionally run, and write timings, XLA's memory analysis and peak RSS to OUT_JSON.
  SPEC["program"]  "train": trainer.train over SPEC["seeds"] seeds (the whole run as one
                   program); "chunk": what hds.run compiles, trainer.run_chunk over the seeds
                   after a jitted init, mapped over the seeds as hds.run maps them (one run's
                   program called on each, hds.utils.runtime.RunByRun, with init compiled
                   and run while the chunk compiles, start_and_compile; or over_runs)
  SPEC["vmapped"]  how many seeds are vmapped at a time, as hds.run's `vmap_runs` (default
                   null: what hds.run does here; 0: all; 1: a loop over them)
  SPEC["run"]      run the compiled program (default true): a first call (`first_run_s`, which
                   also pays first-call allocations), then up to SPEC["repeats"] more (default
                   0) while they take less than SPEC["repeat_s"] seconds in all (default 30);
                   `run_s` is their median, or the first call's time where there are none
  SPEC["cache"]    a persistent compilation cache directory (default: none, a cold compile)

KIND `programs`: run `hds.run`'s experiment of SPEC["overrides"] in-process on the empty
persistent cache SPEC["cache"], and write every program's trace, lowering and XLA compile
seconds (jax's own log records of them) and the trainer chunk's size in ops.
"""

from __future__ import annotations

import time

_START = time.perf_counter()

import json  # noqa: E402
import logging  # noqa: E402
import re  # noqa: E402
import sys  # noqa: E402

from hds.utils.runtime import headless_mujoco  # noqa: E402

headless_mujoco()  # as hds.run does, before hds's modules import MuJoCo

from bench.common import best_of, block, compose, peak_rss_mb, timed  # noqa: E402
from hds.experiment import trainer_program_key  # noqa: E402
from hds.utils.runtime import (  # noqa: E402
    RunByRun,
    command_gc,
    over_runs,
    runs_vmapped,
    start_and_compile,
)


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
    # the seeds as hds.experiment.compiled_programs gives them (a host array: no eager iota)
    keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray(list(range(seeds))))
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
    if spec.get("program", "train") == "chunk" and vmapped == 1:
        # as hds.run: one run's program, called on each run (RunByRun), kept in the program
        # cache beside the compilation cache (hds.experiment's key); init compiled and run on a
        # second thread while the chunk is traced and compiled (init_s: init traced; compile_s:
        # the chunk compiled, init compiled and run)
        init = RunByRun(trainer.init, key=trainer_program_key(cfg, trainer.init))
        chunk = RunByRun(trainer.run_chunk, key=trainer_program_key(cfg, trainer.run_chunk))
        timing: dict = {}
        state, compiled = start_and_compile(init, chunk, keys, hparams, timing=timing)
        args = (block(state), hparams)
        out.update(timing, epochs_per_call=trainer.chunk)
    else:
        if spec.get("program", "train") == "chunk":
            init = jax.jit(over_runs(trainer.init, vmapped, seeds))
            chunk = jax.jit(over_runs(trainer.run_chunk, vmapped, seeds))
            with timed() as init_t:
                state = block(init(keys, hparams))
            fn, args = chunk, (state, hparams)
            out.update(init_s=init_t.s, epochs_per_call=trainer.chunk)
        else:
            fn, args = jax.jit(over_runs(trainer.train, vmapped, seeds)), (keys, hparams)
        with timed() as trace:
            lowered = fn.lower(*args)
        with timed() as comp:
            compiled = lowered.compile()
        out.update(trace_s=trace.s, compile_s=comp.s)
    out["memory"] = memory_analysis(getattr(compiled, "program", compiled))  # RunByRun: one run's
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


# jax logs each program's trace, lowering and XLA compile (DEBUG; WARNING under
# jax_log_compiles) with these messages; their format is jax's, so a record that no longer
# matches is counted in `unparsed`, not misread
COMPILE_LOGS = {
    "trace_s": re.compile(r"Finished tracing \+ transforming (.+) for pjit in ([0-9.e-]+) sec"),
    "lower_s": re.compile(r"Finished jaxpr to MLIR module conversion (.+) in ([0-9.e-]+) sec"),
    "compile_s": re.compile(r"Finished XLA compilation of (.+) in ([0-9.e-]+) sec"),
}


class CompileLog(logging.Handler):
    """Collects jax's per-program trace, lowering and compile seconds, by program name."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.programs: dict[str, dict] = {}
        self.unparsed = 0

    def emit(self, record):
        message = record.getMessage()
        if not message.startswith("Finished"):
            return
        for field, pattern in COMPILE_LOGS.items():
            if m := pattern.search(message):
                name = m.group(1).removeprefix("jit(").removesuffix(")")
                entry = self.programs.setdefault(name, {"count": 0})
                entry[field] = entry.get(field, 0.0) + float(m.group(2))
                entry["count"] += field == "compile_s"
                return
        self.unparsed += 1


def hlo_size(lowered) -> dict:
    """A program's size: StableHLO ops as traced and lowered, and HLO instructions after
    XLA's optimisation (what it generated code for)."""
    text = lowered.as_text()
    ops = len(re.findall(r"^\s*(?:%\S+(?:, %\S+)* = )?\"?(?:stablehlo|chlo)\.", text, re.M))
    hlo = lowered.compile().as_text() or ""
    instructions = len(re.findall(r"^\s*(?:ROOT )?%?[\w.\-]+ = ", hlo, re.M))
    return {"stablehlo_ops": ops, "hlo_instructions": instructions}


def programs(spec: dict) -> dict:
    """Run `hds.run`'s experiment on SPEC["overrides"] in this process (SPEC["cache"]: an empty
    persistent cache) and report every program jax traced, lowered and compiled on the way
    (trainer chunk, evaluation, the dynamics model's training, discovery's fit, and the small
    eager ones), then the size of the trainer's chunk program."""
    import tempfile

    import jax

    from hds import experiment
    from hds.algo.pods import make_train_from_config
    from hds.envs import make_env
    from hds.utils.runtime import enable_compilation_cache

    enable_compilation_cache(spec["cache"])
    handler = CompileLog()
    dispatch = logging.getLogger("jax._src.dispatch")
    dispatch.setLevel(logging.DEBUG)
    dispatch.addHandler(handler)
    dispatch.propagate = False  # DEBUG records stay here, off the console
    import_s = time.perf_counter() - _START
    cfg = compose(*spec["overrides"])
    with tempfile.TemporaryDirectory(prefix="hds-bench-run-") as out, timed() as run:
        experiment.run(cfg, out, experiment.Hooks(console=False))
    dispatch.removeHandler(handler)
    # the trainer's program of the configuration's first method: its size (XLA's compile comes
    # from the persistent cache the run filled; tracing and lowering are done again)
    trainer = make_train_from_config(cfg, make_env(cfg.env))
    state = jax.eval_shape(trainer.init, jax.random.PRNGKey(0), trainer.default_hparams)
    size = hlo_size(jax.jit(trainer.run_chunk).lower(state, trainer.default_hparams))
    return {
        "import_s": import_s,
        "run_s": run.s,
        "programs": handler.programs,
        "unparsed": handler.unparsed,
        "chunk_size": size,
        "epochs_per_chunk": trainer.chunk,
        "peak_rss_mb": peak_rss_mb(),
    }


KINDS = {"train": train, "programs": programs}


def main() -> None:
    command_gc()  # as hds.run does
    kind, spec, path = sys.argv[1], json.loads(sys.argv[2]), sys.argv[3]
    result = KINDS[kind](spec)
    with open(path, "w") as f:
        json.dump(result, f)


if __name__ == "__main__":
    main()
