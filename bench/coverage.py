"""Section `coverage`: how often discovery's 95% intervals hold the truth.

Each effect of the library is hidden, alone, at several magnitudes in the C MuJoCo plant
(whose laws are MuJoCo's own where it has one: frictionloss is a soft constraint, not the
library's tanh), with Gaussian measurement noise, and `hds.discover.discover` runs on the
default simulator, told nothing. A case counts towards coverage when the hidden effect is
named; it covers when every parameter's interval holds the hidden value (a delay: the hidden
steps lie among the steps the data cannot rule out). Target: 90 to 98%. `seeds` repeats every
case on that many recordings (other excitations and noise); coverage comes with its 95%
Clopper-Pearson interval over the named cases.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from bench.common import compose, timed
from bench.discovery import record

DEFAULT_BUDGET = {"episodes": 12, "steps": 80, "noise": 0.005, "stride": 2, "seed": 0, "seeds": 10}

# Every effect of the library at three magnitudes, on the cart-pole (actuator range +-3,
# gear 100; the excitation uses 15% of the range).
CASES = [
    ("coulomb_friction", "slider", "force", (5.0, 12.0, 25.0)),
    ("viscous_damping", "hinge", "coefficient", (0.1, 0.3, 0.6)),
    ("actuator_gain", "slide", "gain", (0.6, 0.85, 1.3)),
    ("actuator_offset", "slide", "offset", (-0.1, 0.05, 0.15)),
    ("actuator_deadzone", "slide", "width", (0.1, 0.3, 0.5)),
    ("action_delay", "slide", "steps", (1, 2, 3)),
    ("actuator_lag", "slide", "time_constant", (0.04, 0.1, 0.2)),
    ("mass_scale", "pole", "scale", (0.7, 1.5, 2.0)),
    ("sensor_bias", "q_hinge", "bias", (-0.1, 0.05, 0.2)),
]


def run(budget: dict) -> dict:
    from hds.discover import DiscoverConfig, discover
    from hds.envs import make_env
    from hds.real.mujoco_plant import MujocoPlant

    cfg = compose("env.backend=analytic")
    task = make_env(cfg.env).task
    settings = DiscoverConfig(stride=int(budget["stride"]))
    rows = []
    hidden_cases = [(n, t, p, v) for n, t, p, values in CASES for v in values]
    for repeat in range(int(budget["seeds"])):
        for case, (name, target, param, value) in enumerate(hidden_cases):
            hidden = {"name": name, "target": target, "params": {param: value}}
            plant = MujocoPlant(cfg.env, [hidden])
            seed = int(budget["seed"]) + case + repeat * len(hidden_cases)
            data = record(plant, task, budget["episodes"], budget["steps"], seed)
            spread = data.obs.max(axis=(0, 1)) - data.obs.min(axis=(0, 1))
            noise = np.random.default_rng(seed + 7).normal(size=data.obs.shape)
            data.obs = data.obs + budget["noise"] * spread * noise
            with timed() as t:
                result = discover(data, cfg.env, settings)
            found = {(e.name, e.target): e for e in result.missing_effects}.get((name, target))
            lo, hi = found.ci95[param] if found else (np.nan, np.nan)
            rows.append(
                {
                    "effect": f"{name}@{target}",
                    "param": param,
                    "truth": value,
                    "named": found is not None,
                    "fitted": found.params[param] if found else np.nan,
                    "lo": lo,
                    "hi": hi,
                    "covers": bool(found is not None and lo <= value <= hi),
                    "others": [
                        f"{e.name}@{e.target}" for e in result.missing_effects if e is not found
                    ],
                    "seed": seed,
                    "seconds": t.s,
                }
            )
    named = [r for r in rows if r["named"]]
    covered = sum(r["covers"] for r in named)
    coverage = covered / max(len(named), 1)
    low, high = stats.binomtest(covered, max(len(named), 1)).proportion_ci(0.95)
    width = [
        (r["hi"] - r["lo"]) / max(abs(r["truth"]), 1e-9) for r in named if r["param"] != "steps"
    ]
    return {
        "title": "coverage of discovery's 95% intervals",
        "tables": [
            {
                "caption": f"Each effect hidden alone in the C MuJoCo plant, "
                f"{budget['seeds']} recording(s) each ({budget['episodes']} episodes x "
                f"{budget['steps']} steps, noise {budget['noise']:.1%} of each signal's range); "
                "coverage "
                f"{coverage:.1%} of {len(named)} named cases ({len(rows)} hidden)",
                "columns": [
                    "effect",
                    "seed",
                    "param",
                    "truth",
                    "fitted",
                    "95% interval",
                    "holds",
                    "also named",
                    "s",
                ],
                "rows": [
                    [
                        r["effect"],
                        r["seed"],
                        r["param"],
                        r["truth"],
                        r["fitted"],
                        f"[{r['lo']:.4g}, {r['hi']:.4g}]" if r["named"] else "not named",
                        "yes" if r["covers"] else "no",
                        ", ".join(r["others"]) or "-",
                        r["seconds"],
                    ]
                    for r in rows
                ],
            }
        ],
        "notes": [
            f"Coverage: {covered} of {len(named)} named cases ({coverage:.1%}, 95% "
            f"Clopper-Pearson interval {low:.1%} to {high:.1%}; target 90-98%); named: "
            f"{len(named)} of {len(rows)} hidden.",
            f"Median relative width of the continuous parameters' intervals: "
            f"{np.median(width) if width else float('nan'):.1%} of the hidden value.",
            "Not held: "
            + (
                "; ".join(
                    f"{r['effect']} {r['truth']:.4g} (seed {r['seed']}): fitted {r['fitted']:.4g}, "
                    f"[{r['lo']:.4g}, {r['hi']:.4g}]"
                    for r in named
                    if not r["covers"]
                )
                or "none"
            )
            + ".",
        ],
        "data": {"rows": rows, "coverage": coverage, "coverage_ci95": [low, high]},
    }
