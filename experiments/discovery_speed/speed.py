"""Issue 38.2's speed target: gap discovery on a 20 x 200-step record with 0.3% noise, warm
(compiles from the persistent cache, a second process), on 2 cores.

The record is bench.discovery's (the default plant: C MuJoCo with 20 N of hidden rail
friction, random force steps from random states), plus Gaussian noise of 0.3% of each
signal's standard deviation (`--of range`: of its range, as bench.coverage adds it). Prints
discover()'s stage timings, what it named, and with --profile the top of cProfile's table.

    PYTHONPATH=$PWD .venv/bin/python experiments/discovery_speed/speed.py [--of std|range]
        [--noise 0.003] [--profile] [--repeat 2]
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import time

import numpy as np

from bench.common import compose
from bench.discovery import record
from hds.discover import discover
from hds.discover.config import DiscoverConfig
from hds.envs import make_env
from hds.real.mujoco_plant import MujocoPlant
from hds.utils.runtime import enable_compilation_cache


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--noise", type=float, default=0.003)
    parser.add_argument("--of", choices=("std", "range"), default="std")
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    enable_compilation_cache()
    cfg = compose("env.backend=analytic")
    env = make_env(cfg.env)
    plant = MujocoPlant(
        cfg.env, [{"name": "coulomb_friction", "target": "slider", "params": {"force": 20.0}}]
    )
    data = record(plant, env.task, 20, 200, 0)
    spread = data.obs.std(axis=(0, 1)) if args.of == "std" else np.ptp(data.obs, axis=(0, 1))
    data.obs = data.obs + args.noise * spread * np.random.default_rng(7).normal(size=data.obs.shape)
    for i in range(args.repeat):
        profiler = cProfile.Profile() if args.profile and i == args.repeat - 1 else None
        t0, c0 = time.perf_counter(), time.process_time()
        if profiler:
            profiler.enable()
        result = discover(data, cfg.env, DiscoverConfig())
        if profiler:
            profiler.disable()
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        named = [f"{e.name}@{e.target} {e.fitted()}" for e in result.missing_effects]
        print(
            f"run {i}: {wall:.1f} s wall, {cpu:.1f} s CPU, load {os.getloadavg()}, initial states "
            f"{result.initial_state}; named {named}; unexplained "
            f"{result.unexplained_fraction:.3f}; stopped: {result.stopped}"
        )
        for r in sorted({row["round"] for row in result.candidates}):
            its = [row["iterations"] for row in result.candidates if row["round"] == r]
            print(
                f"  round {r}: LM iterations sum {sum(its)}, median {np.median(its):.0f}, "
                f"max {max(its)}"
            )
            slow = [
                f"{row['name']}@{row['target']} {row['params']}: {row['iterations']}"
                for row in result.candidates
                if row["round"] == r and row["iterations"] >= 10
            ]
            print(f"    the rows of 10 or more: {slow}")
        print("  timing", {k: round(v, 2) for k, v in result.timing.items()}, flush=True)
        if profiler:
            pstats.Stats(profiler).sort_stats("cumulative").print_stats(45)


if __name__ == "__main__":
    main()
