"""Discovery's cost per recorded step (issue 41): wall time and peak memory of `hds.discover.
discover` on cart-pole data of E episodes x T steps recorded on a MuJoCo plant with 20 N of rail
friction, one size per process (peak RSS is per process). The constants in hds/data/budget.py
come from this.

  PYTHONPATH=$PWD python experiments/large_data/calibrate.py 8 250   # prints one JSON line
  PYTHONPATH=$PWD python experiments/large_data/calibrate.py 8 250 fit  # an MLP's fit instead
"""

from __future__ import annotations

import json
import resource
import sys
import time

import numpy as np

from hds.config import compose
from hds.data import collect, random_steps
from hds.discover import discover
from hds.envs import make_env
from hds.real.mujoco_plant import MujocoPlant
from hds.utils.runtime import enable_compilation_cache


def main(episodes: int, steps: int, work: str = "discovery") -> dict:
    enable_compilation_cache()
    cfg = compose(["env.backend=analytic"])
    task = make_env(cfg.env).task
    plant = MujocoPlant(
        cfg.env, [{"name": "coulomb_friction", "target": "slider", "params": {"force": 20.0}}]
    )
    rng = np.random.default_rng(0)
    q0 = np.c_[rng.uniform(-0.5, 0.5, episodes), rng.uniform(-np.pi, np.pi, episodes)]
    qd0 = rng.uniform(-0.5, 0.5, (episodes, 2))
    u = random_steps(1, episodes, steps, plant.dt, plant.ctrl_range, 0.1, 0.5, scale=0.15)
    data = collect(plant, task, q0, qd0, u, steps)
    start = time.perf_counter()
    if work == "fit":  # 10 epochs, no early stop: the time per step and epoch
        from dataclasses import replace

        from hds.dynamics import fit

        dyn = replace(cfg.dynamics, model="mlp", epochs=10, patience=10)
        _, report = fit(dyn, make_env(cfg.env), data, compare_simulator=False)
        named = [f"{report['epochs_run']} epochs, fit_s {report['fit_s']}"]
    else:
        result = discover(data, cfg.env, cfg.discover)
        named = [e.name for e in result.missing_effects]
    seconds = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {
        "work": work,
        "episodes": episodes,
        "steps": steps,
        "recorded_steps": episodes * steps,
        "seconds": round(seconds, 1),
        "peak_rss_gb": round(peak / 1e9, 3),
        "named": named,
    }


if __name__ == "__main__":
    print(json.dumps(main(int(sys.argv[1]), int(sys.argv[2]), *sys.argv[3:])), flush=True)
