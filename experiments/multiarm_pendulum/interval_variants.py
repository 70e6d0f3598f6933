"""The law-mismatch bound of discovery's intervals, measured: coverage of the coverage bench's
cases (`bench/coverage.py`: each library effect hidden alone in the C MuJoCo plant, 0.5%
noise) with each named case's interval recomputed from its own fit without the bound, without
the views, or with the noise part alone (`confidence_intervals` on the final state's H, G,
misfit and views). Decisions are discovery's own; only the reported interval varies.

    python experiments/multiarm_pendulum/interval_variants.py --seeds 10
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy import stats

from bench.common import compose
from bench.coverage import CASES, DEFAULT_BUDGET
from bench.discovery import record
from hds.discover import DiscoverConfig, discover
from hds.discover.fit import confidence_intervals
from hds.envs import make_env
from hds.real.mujoco_plant import MujocoPlant
from hds.utils.io import atomic_write_json

HERE = Path(__file__).resolve().parent
VARIANTS = {
    "reported (noise + misfit bound + views)": lambda s: (s.misfit, s.views),
    "noise + views (no misfit bound)": lambda s: (0.0, s.views),
    "noise + misfit bound (no views)": lambda s: (s.misfit,),
    "noise alone": lambda s: (),
}


def halves(state, slot: int) -> dict[str, float]:
    theta = state.theta[state.slots]
    i = state.slots.index(slot)
    return {
        name: float(confidence_intervals(theta, state.h, state.g, *extra(state)).half[i])
        for name, extra in VARIANTS.items()
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=DEFAULT_BUDGET["seeds"])
    args = parser.parse_args(argv)
    budget = DEFAULT_BUDGET | {"seeds": args.seeds}
    cfg = compose("env.backend=analytic")
    task = make_env(cfg.env).task
    settings = DiscoverConfig(stride=int(budget["stride"]))
    cases = [(n, t, p, v) for n, t, p, values in CASES for v in values]
    rows, start = [], time.perf_counter()
    for repeat in range(args.seeds):
        for case, (name, target, param, value) in enumerate(cases):
            plant = MujocoPlant(
                cfg.env, [{"name": name, "target": target, "params": {param: value}}]
            )
            seed = int(budget["seed"]) + case + repeat * len(cases)
            data = record(plant, task, budget["episodes"], budget["steps"], seed)
            spread = data.obs.max(axis=(0, 1)) - data.obs.min(axis=(0, 1))
            noise = np.random.default_rng(seed + 7).normal(size=data.obs.shape)
            data.obs = data.obs + budget["noise"] * spread * noise
            result = discover(data, cfg.env, settings)
            # the state the named effects' intervals come from (`workflow.discover`)
            state = result.selection.states[len(result.missing_effects)]
            cand = next((c for c in state.selected if (c.name, c.target) == (name, target)), None)
            row = {"effect": f"{name}@{target}", "param": param, "truth": value, "seed": seed}
            if cand is not None and not cand.shifts_actions:
                slot = cand.slots[cand.params.index(param)]
                row |= {"fitted": float(state.theta[slot]), "half": halves(state, slot)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    named = [r for r in rows if "half" in r]
    summary = {}
    for variant in VARIANTS:
        held = sum(abs(r["fitted"] - r["truth"]) <= r["half"][variant] for r in named)
        low, high = stats.binomtest(held, max(len(named), 1)).proportion_ci(0.95)
        summary[variant] = {"held": held, "named": len(named), "ci95": [low, high]}
        print(
            f"{variant}: {held}/{len(named)} = {held / max(len(named), 1):.1%} "
            f"[{low:.1%}, {high:.1%}]"
        )
    out = {"date": "2026-11-27", "seeds": args.seeds, "seconds": time.perf_counter() - start}
    atomic_write_json(HERE / "interval_variants.json", out | {"summary": summary, "rows": rows})


if __name__ == "__main__":
    main()
