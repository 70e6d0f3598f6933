"""Section `gpu`: skipped on a CPU-only machine. A GPU run of the other sections is recorded
separately (by whoever has a device lent): `python -m bench.run reference overhead ...` there,
whose results carry that machine's description."""

from __future__ import annotations

import jax

DEFAULT_BUDGET: dict = {}


def run(budget: dict) -> dict:
    title = "accelerator"
    backend = jax.default_backend()
    if backend == "cpu":
        return {
            "title": title,
            "skipped": "jax runs on CPU here (no GPU); the GPU numbers are recorded "
            "separately, by running the other sections on a machine with one.",
        }
    return {
        "title": title,
        "skipped": f"jax's default backend is {backend}: every other section already ran "
        "on it (see the machine line of each section).",
        "data": {"devices": [str(d) for d in jax.devices()]},
    }
