"""Section `terms`: effects outside the library, found as sparse force terms and added.

Two effects no named effect of the library has, each hidden in a plant over several seeds
(a seed: other initial states and excitation), and `hds.discover.discover` run on the default
simulator, told nothing:
  spring  a rail spring, MJCF joint stiffness in the C MuJoCo plant: expect a term -k q
  drag    air drag on the pole, -c |qd| qd (joint_force_terms in the exact brax plant), with
          terms fitted once the library leaves `terms_threshold` of the error
          (discover.unexplained_warning): viscous damping stands in for most of it
Reported: the expected term's coefficient, the other terms and named effects, and the held-out
k-step error (normalized RMSE) of the simulator as it is, with the named effects, and with
the terms too (the corrected simulator).
"""

from __future__ import annotations

import dataclasses
import tempfile
from pathlib import Path

import numpy as np

from bench.common import compose, summary, timed
from bench.discovery import record

DEFAULT_BUDGET = {
    "episodes": 12,
    "steps": 80,
    "stride": 2,
    "seeds": 5,
    "stiffness": 30.0,  # N/m
    "drag": 0.2,  # N m s^2/rad^2
    "terms_threshold": 0.05,
}


def plants(env_cfg, budget: dict, folder: Path) -> dict:
    """{case: (plant, joint, term, true coefficient, discover settings)}."""
    from hds.discover import DiscoverConfig
    from hds.envs import make_env
    from hds.envs.system import load_spec
    from hds.real.brax_plant import BraxPlant
    from hds.real.mujoco_plant import MujocoPlant

    spec = load_spec(env_cfg.xml)
    spec.joint("slider").stiffness[0] = budget["stiffness"]
    path = folder / "cartpole_spring.xml"
    path.write_text(spec.to_xml())
    spring = MujocoPlant(dataclasses.replace(env_cfg, xml=str(path)))
    hidden = {"name": "joint_force_terms", "target": "hinge"}
    hidden["params"] = {"abs_qd_qd": -budget["drag"]}
    drag = BraxPlant(make_env(env_cfg, effects=[hidden], sharpness=None))
    settings = DiscoverConfig(stride=int(budget["stride"]))
    low = dataclasses.replace(settings, unexplained_warning=float(budget["terms_threshold"]))
    return {
        "spring": (spring, "slider", "q", -budget["stiffness"], settings),
        "drag": (drag, "hinge", "|qd| qd", -budget["drag"], low),
    }


def measure(case: str, spec: tuple, env_cfg, task, budget: dict, seed: int) -> dict:
    from hds.discover import discover

    plant, joint, term, truth, settings = spec
    data = record(plant, task, budget["episodes"], budget["steps"], seed)
    with timed() as t:
        result = discover(data, env_cfg, settings)
    found = {(x.joint, x.term): x for x in result.terms}.get((joint, term))
    with_terms = result.after_terms["heldout"][1].normalized if result.terms else np.nan
    return {
        "case": case,
        "seed": seed,
        "truth": truth,
        "fitted": found.coefficient if found else np.nan,
        "relative_error": abs(found.coefficient / truth - 1) if found else np.nan,
        "other_terms": [
            f"{x.coefficient:.4g} x {x.term}@{x.joint}" for x in result.terms if x is not found
        ],
        "named": [f"{e.name}@{e.target}" for e in result.missing_effects],
        "unexplained": result.unexplained_fraction,
        "before": result.error("before").normalized,
        "named_only": result.error("after").normalized,
        "with_terms": with_terms,
        "seconds": t.s,
    }


def run(budget: dict) -> dict:
    from hds.envs import make_env

    cfg = compose("env.backend=analytic")
    task = make_env(cfg.env).task
    with tempfile.TemporaryDirectory() as folder:
        cases = plants(cfg.env, budget, Path(folder))
        rows = [
            measure(case, spec, cfg.env, task, budget, seed)
            for case, spec in cases.items()
            for seed in range(int(budget["seeds"]))
        ]
    notes = []
    for case in cases:
        mine = [r for r in rows if r["case"] == case]
        found = [r for r in mine if np.isfinite(r["fitted"])]
        fitted = summary([r["fitted"] for r in found]) if found else None
        shrink = summary([r["named_only"] / r["with_terms"] for r in found]) if found else None
        notes.append(
            f"{case}: the term found in {len(found)} of {len(mine)} seeds"
            + (
                f", coefficient {fitted['mean']:.4g} (range {fitted['min']:.4g} to "
                f"{fitted['max']:.4g}; truth {mine[0]['truth']:g}); the terms divide the named "
                f"effects' held-out error by {shrink['mean']:.3g} (range {shrink['min']:.3g} "
                f"to {shrink['max']:.3g})"
                if found
                else ""
            )
        )
    return {
        "title": "effects outside the library: sparse force terms",
        "tables": [
            {
                "caption": f"Hidden effects outside the library ({budget['episodes']} episodes x "
                f"{budget['steps']} steps, no noise); held-out k-step error in normalized RMSE",
                "columns": [
                    "case",
                    "seed",
                    "truth",
                    "fitted",
                    "other terms",
                    "named",
                    "unexplained",
                    "error as is",
                    "named effects",
                    "with terms",
                    "s",
                ],
                "rows": [
                    [
                        r["case"],
                        r["seed"],
                        r["truth"],
                        r["fitted"],
                        "; ".join(r["other_terms"]) or "-",
                        ", ".join(r["named"]) or "-",
                        r["unexplained"],
                        r["before"],
                        r["named_only"],
                        r["with_terms"],
                        r["seconds"],
                    ]
                    for r in rows
                ],
            }
        ],
        "notes": notes,
        "data": {"rows": rows},
    }
