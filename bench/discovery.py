"""Section `discovery`: time to a gap-discovery report on 20 episodes x 200 steps of measured
data. Skipped, with a note, where the module `hds.discover` does not exist.

Data: the "real" plant of the default config (C MuJoCo with a hidden 20 N Coulomb friction on
the slider, conf/real/mujoco.yaml) driven by random force steps (held 0.1 to 0.5 s, 15 % of the
actuator range) from random states with the pole anywhere. Then `hds.discover.discover` on the
default simulator (env=cartpole_balance) on each backend of the budget, and `write_report`
into a temporary directory: the time a user waits for report.md after having the data.

Each row fits on its own backend (`discover.backend` set to it: the default, auto, would fit on
the analytic backend whatever the env's), and starts with discovery's engine cache and JAX's
in-memory caches emptied, so each row pays its own compiles. Per backend three rows: in this
process with no persistent compilation cache; then, each in a fresh process
(`python -m bench.discovery SPEC OUT`), cold on an empty persistent cache directory and warm, a
second process on the same directory (hds.utils.runtime.enable_compilation_cache, as
`python -m hds.discover` enables it). JAX's own compile events (jax.monitoring) split each
row's time into tracing, lowering, XLA compile (or persistent-cache load) and the rest; the
Engine's entry points (fit, errors, predictions) are counted and timed, and the process's CPU
seconds recorded beside the wall seconds (the machine may be shared).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from bench.common import ROOT, compose, timed

DEFAULT_BUDGET = {
    "episodes": 20,
    "steps": 200,
    "seed": 0,
    "stride": 1,  # DiscoverConfig's default: a k-step window starts at every step
    # generalized (the default env's backend) takes about 11 minutes here: add it with
    # --set discovery.backends=analytic,generalized
    "backends": ["analytic"],
}


def record(plant, task, episodes: int, steps: int, seed: int):
    from hds.data.collect import collect
    from hds.data.excitation import random_steps

    rng = np.random.default_rng(seed)
    q0 = np.c_[rng.uniform(-0.5, 0.5, episodes), rng.uniform(-np.pi, np.pi, episodes)]
    qd0 = rng.uniform(-0.5, 0.5, (episodes, 2))
    u = random_steps(
        seed + 1,
        episodes,
        steps,
        plant.dt,
        plant.ctrl_range,
        min_hold=0.1,
        max_hold=0.5,
        scale=0.15,
    )
    return collect(plant, task, q0, qd0, u)


COMPILE_EVENTS = {
    "trace": "/jax/core/compile/jaxpr_trace_duration",
    "lower": "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "compile": "/jax/core/compile/backend_compile_duration",  # a persistent-cache load too
    "cache_load": "/jax/compilation_cache/cache_retrieval_time_sec",  # hits only
}


class CompileLog:
    """JAX's compile events (jax.monitoring) while open: `seconds` and `counts` per kind of
    COMPILE_EVENTS (counts["compile"]: programs compiled or loaded; counts["cache_load"]:
    of them, loaded from the persistent cache)."""

    def __enter__(self):
        import jax

        self.seconds, self.counts = defaultdict(float), defaultdict(int)
        self._kinds = {event: kind for kind, event in COMPILE_EVENTS.items()}
        jax.monitoring.register_event_duration_secs_listener(self._record)
        return self

    def _record(self, event: str, secs: float, **_) -> None:
        kind = self._kinds.get(event)
        if kind is not None:
            self.seconds[kind] += secs
            self.counts[kind] += 1

    def __exit__(self, *exc):
        import jax

        jax.monitoring.unregister_event_duration_listener(self._record)


ENGINE_CALLS = ("fit", "errors", "predictions")  # discovery's compiled work, by entry point


class EngineLog:
    """Calls and wall seconds of each host-side entry point of discovery's Engine while open.
    Each returns numpy arrays, so a call's seconds hold its run and, on the first call of a
    program, its tracing and compile."""

    def __enter__(self):
        from hds.discover.fit import Engine

        self.calls, self.seconds = defaultdict(int), defaultdict(float)
        self._originals = {name: getattr(Engine, name) for name in ENGINE_CALLS}
        for name, method in self._originals.items():
            setattr(Engine, name, self._timed(name, method))
        return self

    def _timed(self, name: str, method):
        def timed_call(*args, **kwargs):
            start = time.perf_counter()
            out = method(*args, **kwargs)
            self.calls[name] += 1
            self.seconds[name] += time.perf_counter() - start
            return out

        return timed_call

    def __exit__(self, *exc):
        from hds.discover.fit import Engine

        for name, method in self._originals.items():
            setattr(Engine, name, method)


def in_process(spec: dict) -> dict:
    """One row in a fresh process (`python -m bench.discovery SPEC OUT`), with the persistent
    compilation cache of spec["cache"]."""
    with tempfile.TemporaryDirectory(prefix="hds-bench-") as tmp:
        out = Path(tmp) / "row.json"
        cmd = [sys.executable, "-m", "bench.discovery", json.dumps(spec), str(out)]
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1800)
        if proc.returncode != 0 or not out.exists():
            tail = (proc.stderr or proc.stdout)[-2000:]
            raise RuntimeError(f"bench.discovery row failed (rc {proc.returncode}):\n{tail}")
        return json.loads(out.read_text())


def rows_of(backend: str, budget: dict) -> list[dict]:
    """The backend's three rows: in this process without a persistent cache; in fresh
    processes on an empty persistent cache directory (cold), then on the same one (warm)."""
    rows = [{**measure(backend, budget), "cache": "none (in-process)"}]
    cache = Path(tempfile.mkdtemp(prefix="hds-bench-cache-"))
    try:
        spec = {"backend": backend, "budget": budget, "cache": str(cache)}
        rows.append({**in_process(spec), "cache": "empty (new process)"})
        rows.append({**in_process(spec), "cache": "warm (new process)"})
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    return rows


def run(budget: dict) -> dict:
    title = "time to a gap-discovery report"
    runs = [row for backend in budget["backends"] for row in rows_of(backend, budget)]
    stages = sorted({k for r in runs for k in r["timing"]})
    return {
        "title": title,
        "tables": [
            {
                "caption": f"Seconds ({budget['episodes']} episodes x {budget['steps']} steps "
                f"from the {runs[0]['plant']} plant; simulator env={runs[0]['env']} on each "
                "backend; discover()'s stages from Result.timing)",
                "columns": [
                    "backend",
                    "persistent cache",
                    "env + plant build",
                    "data collection",
                    "discover()",
                    *[f"of which {k}" for k in stages],
                    "write_report()",
                    "data to report",
                ],
                "rows": [
                    [
                        r["backend"],
                        r["cache"],
                        r["build_s"],
                        r["collect_s"],
                        r["discover_s"],
                        *[r["timing"].get(k) for k in stages],
                        r["report_s"],
                        r["collect_s"] + r["discover_s"] + r["report_s"],
                    ]
                    for r in runs
                ],
            },
            {
                "caption": "discover() + write_report(): CPU seconds (user + sys, all threads of "
                "the process: the machine is shared, wall seconds are inflated by its load) and "
                "discovery's compiled work by entry point (calls, wall seconds including the "
                "first call's tracing and compile; fit: the batched Levenberg-Marquardt fits, "
                "errors: held-out and identification k-step errors, predictions: compare's "
                "residuals)",
                "columns": [
                    "backend",
                    "persistent cache",
                    "wall s",
                    "CPU s",
                    *[f"Engine.{k} {u}" for k in ENGINE_CALLS for u in ("calls", "s")],
                    "outside Engine s",
                ],
                "rows": [
                    [
                        r["backend"],
                        r["cache"],
                        r["discover_s"] + r["report_s"],
                        r["cpu_s"],
                        *[r["engine"][k][i] for k in ENGINE_CALLS for i in (0, 1)],
                        r["discover_s"]
                        + r["report_s"]
                        - sum(r["engine"][k][1] for k in ENGINE_CALLS),
                    ]
                    for r in runs
                ],
            },
            {
                "caption": "Where discover() + write_report() spend their seconds (JAX's "
                "compile events; programs: distinct XLA programs compiled or loaded, of which "
                "from the persistent cache)",
                "columns": [
                    "backend",
                    "persistent cache",
                    "discover() + write_report()",
                    "tracing",
                    "lowering",
                    "XLA compile or cache load",
                    "running and host work",
                    "programs",
                    "from cache",
                ],
                "rows": [
                    [
                        r["backend"],
                        r["cache"],
                        r["discover_s"] + r["report_s"],
                        r["jax_s"]["trace"],
                        r["jax_s"]["lower"],
                        r["jax_s"]["compile"],
                        r["discover_s"]
                        + r["report_s"]
                        - sum(r["jax_s"][k] for k in ("trace", "lower", "compile")),
                        r["programs"]["compile"],
                        r["programs"]["cache_load"],
                    ]
                    for r in runs
                ],
            },
        ],
        "notes": [
            f"{r['backend']}, cache {r['cache']}: hidden in the plant: {r['hidden']}; named "
            "by discovery: "
            + ("; ".join(r["named"]) if r["named"] else "nothing")
            + f" (stopped: {r['stopped']}); linearizations (rows x (1 + iterations)) per "
            f"round of forward selection: {r['linearizations']}."
            for r in runs
        ]
        + [
            "Compile time is included in every row: discovery's engine cache and JAX's "
            "in-memory caches are emptied before each row; the in-process rows share one "
            "process, so only its start-up (imports, JAX's initialisation) falls on the first. "
            "A warm row still traces and lowers (Python work); only XLA's compile comes from "
            "the persistent cache (every program: hds.utils.runtime sets "
            "jax_persistent_cache_min_compile_time_secs to 0)."
        ],
        "data": runs,
    }


def discover_config(cfg, backend: str, stride: int):
    """Discovery's settings for one row: the config's, fitted on `backend` itself."""
    return dataclasses.replace(cfg.discover, backend=backend, stride=stride)


def forget_compiled() -> None:
    """Empty discovery's engine cache and JAX's in-memory caches, so the next row compiles
    its own programs instead of reusing an earlier row's."""
    import jax

    from hds.discover import fit

    fit._ENGINES.clear()
    jax.clear_caches()


def measure(backend: str, budget: dict) -> dict:
    from hds.discover import discover, write_report
    from hds.envs import make_env
    from hds.real import make_plant

    cfg = compose(f"env.backend={backend}")
    forget_compiled()
    with timed() as build:
        env = make_env(cfg.env)
        plant = make_plant(cfg.real, cfg.env)
    with timed() as data_t:
        dataset = record(plant, env.task, budget["episodes"], budget["steps"], budget["seed"])
    cpu_start = time.process_time()
    with CompileLog() as jax_log, EngineLog() as engine_log:
        with timed() as found:
            result = discover(dataset, cfg.env, discover_config(cfg, backend, budget["stride"]))
        if result.backend != backend:  # the row is labelled by the backend the fits ran on
            raise RuntimeError(f"discovery fitted on {result.backend}, not on {backend}")
        with tempfile.TemporaryDirectory(prefix="hds-bench-report-") as out, timed() as written:
            write_report(result, cfg.env, out)
    cpu_s = time.process_time() - cpu_start
    named = [
        f"{e.name} on {e.target}: "
        + ", ".join(f"{k} {v:.3g} {e.units.get(k, '')}".strip() for k, v in e.params.items())
        for e in result.missing_effects
    ]
    return {
        "backend": result.backend,
        "plant": cfg.real.plant,
        "env": cfg.env.name,
        "hidden": ", ".join(f"{e.name} on {e.target} {dict(e.params)}" for e in cfg.real.effects),
        "build_s": build.s,
        "collect_s": data_t.s,
        "discover_s": found.s,
        "report_s": written.s,
        "cpu_s": cpu_s,
        "engine": {k: [engine_log.calls[k], engine_log.seconds[k]] for k in ENGINE_CALLS},
        "timing": dict(result.timing),
        "named": named,
        "stopped": result.stopped,
        # each row of a round's batched fit linearizes once at its start and once per
        # iteration: the work of the round, one row after another
        "linearizations": [
            sum(row["iterations"] + 1 for row in rows) for rows in result.selection.rounds
        ],
        "jax_s": {k: jax_log.seconds[k] for k in COMPILE_EVENTS},
        "programs": {k: jax_log.counts[k] for k in ("compile", "cache_load")},
    }


def main() -> None:
    """`python -m bench.discovery SPEC_JSON OUT_JSON`: one row in this process, with the
    persistent compilation cache of SPEC["cache"]."""
    from hds.utils.runtime import enable_compilation_cache

    spec, out = json.loads(sys.argv[1]), Path(sys.argv[2])
    enable_compilation_cache(spec["cache"])
    out.write_text(json.dumps(measure(spec["backend"], spec["budget"])))


if __name__ == "__main__":
    main()
