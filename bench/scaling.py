"""Section `scaling`: how wall time and memory grow with seeds vmapped in one program, the
horizon, and the rollouts per epoch. Every point is its own process (bench/worker.py), so its
peak RSS is its own; it compiles `jax.jit(jax.vmap(trainer.train))` over the seeds (the whole
training as one program), runs it once, and reports XLA's memory plan of that program too.
Other settings stay at the reference configuration.
"""

from __future__ import annotations

from bench.common import REFERENCE, run_worker

DEFAULT_BUDGET = {
    "backend": "analytic",
    "epochs": 3,
    "seeds": [1, 4, 16, 64],
    "horizons": [50, 100, 200],
    "rollouts": [16, 64, 256],
}


def points(budget: dict) -> list[tuple[str, int, tuple[str, ...], int]]:
    """(axis, value, overrides, seeds) of every point; the base is the reference config with
    `epochs` epochs, 1 seed."""
    base = (*REFERENCE, f"env.backend={budget['backend']}", f"algo.epochs={budget['epochs']}")
    out = [("seeds", n, base, n) for n in budget["seeds"]]
    out += [("horizon", h, (*base, f"env.task.horizon={h}"), 1) for h in budget["horizons"]]
    out += [("rollouts", r, (*base, f"algo.rollouts={r}"), 1) for r in budget["rollouts"]]
    return out


def measure(axis: str, value: int, overrides: tuple[str, ...], seeds: int) -> dict:
    r = run_worker("train", {"overrides": list(overrides), "seeds": seeds, "program": "train"})
    return {"axis": axis, "value": value, **r}


def run(budget: dict) -> dict:
    results = [measure(*p) for p in points(budget)]
    rows = []
    for r in results:
        base = next(b for b in results if b["axis"] == r["axis"])
        mem = r.get("memory") or {}
        rows.append(
            [
                r["axis"],
                r["value"],
                r["compile_s"],
                r["run_s"],
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
                    "run s",
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
            "Seeds are vmapped over the whole training (jax.jit(jax.vmap(train))): on 2 cores, "
            "time grows about linearly with the work once the batch fills the cores.",
        ],
        "data": results,
    }
