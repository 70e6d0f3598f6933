"""Section `scaling`: how wall time and memory grow with the seeds trained in one program
(vmapped, and in a loop as hds.run runs them on one CPU), the horizon, and the rollouts per
epoch. Every point is its own process (bench/worker.py), so its peak RSS is its own; it compiles
the whole training of its seeds as one program (`jax.jit` of trainer.train mapped over them),
runs it once, then again `repeats` times (fewer where they would take over `repeat_s` seconds)
and takes the median of those, and reports XLA's memory plan of that program too. Other
settings stay at the reference configuration.
"""

from __future__ import annotations

from bench.common import REFERENCE, run_worker

DEFAULT_BUDGET = {
    "backend": "analytic",
    "epochs": 3,
    "seeds": [1, 4, 16, 64],
    "horizons": [50, 100, 200],
    "rollouts": [16, 64, 256],
    "repeats": 3,  # timed calls after the first (median); single calls were noisy
    "repeat_s": 30.0,  # ... as many as fit in this many seconds, judged by the first call
    "overrides": [],  # config overrides on top of the reference configuration
}


def points(budget: dict) -> list[tuple[str, int, tuple[str, ...], int, int]]:
    """(axis, value, overrides, seeds, vmapped) of every point; the base is the reference config
    with `epochs` epochs, 1 seed. `vmapped`: seeds vmapped at a time (0 all, 1 a loop)."""
    base = (*REFERENCE, f"env.backend={budget['backend']}", f"algo.epochs={budget['epochs']}")
    base = (*base, *budget["overrides"])
    out = [("seeds, vmapped", n, base, n, 0) for n in budget["seeds"]]
    out += [("seeds, loop", n, base, n, 1) for n in budget["seeds"] if n > 1]
    out += [("horizon", h, (*base, f"env.task.horizon={h}"), 1, 1) for h in budget["horizons"]]
    out += [("rollouts", r, (*base, f"algo.rollouts={r}"), 1, 1) for r in budget["rollouts"]]
    return out


def measure(axis, value, overrides, seeds, vmapped, budget: dict) -> dict:
    spec = {"overrides": list(overrides), "seeds": seeds, "program": "train", "vmapped": vmapped}
    spec.update(repeats=budget["repeats"], repeat_s=budget["repeat_s"])
    return {"axis": axis, "value": value, **run_worker("train", spec)}


def run(budget: dict) -> dict:
    results = [measure(*p, budget) for p in points(budget)]
    rows = []
    for r in results:
        base = next(b for b in results if b["axis"].startswith(r["axis"].split(",")[0]))
        mem = r.get("memory") or {}
        rows.append(
            [
                r["axis"],
                r["value"],
                r["compile_s"],
                r["first_run_s"],
                r["run_s"],
                len(r["repeat_run_s"]),
                r["run_s"] / r["epochs"],
                f"{r['run_s'] / base['run_s']:.2f}x",
                r["peak_rss_mb"],
                r["peak_rss_mb"] - r["rss_after_build_mb"],
                mem.get("temp_mib"),
            ]
        )
    return {
        "title": "seeds, horizon and rollouts: wall time and memory",
        "tables": [
            {
                "caption": f"One process per point, {budget['backend']} backend, "
                f"{budget['epochs']} epochs, reference configuration otherwise "
                "(50 rollouts, horizon 100, 1 seed)",
                "columns": [
                    "axis",
                    "value",
                    "compile s",
                    "first call s",
                    "run s",
                    "calls in median",
                    "s per epoch",
                    "run vs first point",
                    "peak RSS MiB",
                    "RSS growth after build MiB",
                    "XLA temp MiB",
                ],
                "rows": rows,
            }
        ],
        "notes": [
            "Peak RSS: VmHWM of the point's process (Python, jax, brax and the env "
            "included); growth after build: peak minus the peak before tracing, i.e. what "
            "compiling and running the program added. XLA temp: the compiled program's "
            "scratch buffers from compiled.memory_analysis().",
            "First call: the first run of the compiled program (it also pays first-call "
            "allocations); run s: the median of the calls after it (`calls in median`; the "
            "first call's time where none fit in the budget's repeat_s).",
            "Seeds, vmapped: jax.jit(jax.vmap(train)), one batched program; seeds, loop: "
            "jax.jit of jax.lax.map(train), one program running them one after another (what "
            "hds.run does on a single CPU, `vmap_runs` auto). Both rows of a seed count are "
            "compared with the vmapped 1-seed row (a single seed is never vmapped).",
        ],
        "data": results,
    }
