"""Section `gpu`: skipped on a CPU-only machine. On a GPU, `python -m bench.run` runs every
section there and records them apart from the CPU's, in bench/results-gpu.json and
bench/RESULTS-gpu.md (bench.common.result_files), each with that machine's description."""

from __future__ import annotations

import jax

DEFAULT_BUDGET: dict = {}


def run(budget: dict) -> dict:
    title = "accelerator"
    backend = jax.default_backend()
    if backend == "cpu":
        return {
            "title": title,
            "skipped": "jax runs on CPU here (no GPU); `make bench` on a machine with one "
            "records every section there in bench/results-gpu.json and bench/RESULTS-gpu.md.",
        }
    return {
        "title": title,
        "skipped": f"jax's default backend is {backend}: every other section of this file "
        "ran on it (see the machine line of each section).",
        "data": {"devices": [str(d) for d in jax.devices()]},
    }
