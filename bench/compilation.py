"""Section `compile`: cold and warm compile of the trainer, each in its own process.

Cold: a fresh, empty persistent compilation cache directory. Warm: a second process on the same
directory (the persistent cache, `hds.utils.runtime.enable_compilation_cache`, as `python -m
hds.run` enables it). The program is what hds.run compiles: jax.jit of trainer.init and of
trainer.run_chunk mapped over one seed (hds.utils.runtime.over_runs), on the reference
configuration.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from bench.common import REFERENCE, run_worker

DEFAULT_BUDGET = {
    "backends": ["analytic", "generalized"],
    "overrides": [],  # config overrides on top of the reference configuration
}


def entries_of(path: Path) -> set[str]:
    return {p.name for p in path.iterdir()}


def cache_size_mib(path: Path) -> float:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 2**20


def measure(backend: str, overrides: list[str]) -> dict:
    cache = Path(tempfile.mkdtemp(prefix="hds-bench-cache-"))
    try:
        spec = {
            "overrides": [*REFERENCE, f"env.backend={backend}", *overrides],
            "program": "chunk",
            "run": True,
            "cache": str(cache),
        }
        cold = run_worker("train", spec)
        size, entries = cache_size_mib(cache), entries_of(cache)
        warm = run_worker("train", spec)
        new = sorted(entries_of(cache) - entries)
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    # A warm process that writes a new run_chunk entry missed the cache: its program differed
    # from the cold one's (e.g. a source file edited in between, which changes the HLO's
    # source locations).
    return {
        "backend": backend,
        "cold": cold,
        "warm": warm,
        "cache_mib": size,
        "warm_hit": not any("run_chunk" in n for n in new),
        "warm_new_entries": new,
    }


def run(budget: dict) -> dict:
    results = [measure(b, budget["overrides"]) for b in budget["backends"]]
    rows = []
    for r in results:
        for kind in ("cold", "warm"):
            m = r[kind]
            hit = "yes" if kind == "cold" or r["warm_hit"] else "no (missed)"
            rows.append(
                [
                    r["backend"],
                    kind,
                    hit if kind == "warm" else "-",
                    m["import_s"],
                    m["build_s"],
                    m["init_s"],
                    m["trace_s"],
                    m["compile_s"],
                    m["run_s"],
                    m["process_s"],
                ]
            )
    return {
        "title": "cold and warm (persistent cache) compile",
        "tables": [
            {
                "caption": "Seconds, each row its own process (reference configuration"
                + "".join(f", {o}" for o in budget["overrides"])
                + ", 1 seed; run = one compiled chunk of epochs)",
                "columns": [
                    "backend",
                    "cache",
                    "cache hit",
                    "imports",
                    "env build",
                    "init (jit)",
                    "trace",
                    "XLA compile",
                    "run chunk",
                    "process total",
                ],
                "rows": rows,
            }
        ],
        "notes": [
            "Cache sizes after the cold run: "
            + ", ".join(f"{r['backend']} {r['cache_mib']:.1f} MiB" for r in results)
            + ".",
            "A warm process still traces and lowers (Python work); only the XLA compile comes "
            "from the cache. A warm miss means the warm process's program differed from the "
            "cold one's (source files edited in between change the HLO's source locations).",
        ],
        "data": results,
    }
