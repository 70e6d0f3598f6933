"""Issue 38.2, one measurement: what gap discovery names on lab_cartpole draws, against each
draw's truth, and the held-out error it leaves unexplained.

The data are a sim2real loop's first round (hds.loop.record, excite_until_identifiable): a
balance policy trained by closed-loop PODS on the nominal simulator (round 0, the same for
every draw), deployed on the draw's plant, plus open-loop excitation, raised while the data
cannot identify what more excitation would. Discovery runs with its defaults
(discover.effects: the default candidates). Writes experiments/lab_plants/results.json.

    PYTHONPATH=$PWD .venv/bin/python experiments/lab_plants/measure.py [draws=5]
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import jax

from hds import experiment
from hds.config import compose
from hds.data import concatenate
from hds.discover import discover
from hds.envs import make_env
from hds.loop import excite_until_identifiable
from hds.real import lab, make_plant
from hds.utils.io import atomic_write_json, read_json

HERE = Path(__file__).resolve().parent
WORK = Path("outputs/lab_plants")  # checkpoints of round 0 (resumable)
BASE = ["real=lab_cartpole", "method=pods_cl", "env.backend=analytic", "logger=none"]

# what the truth holds for each library effect discovery may name ({effect@target: value})
TRUTH_OF = {
    "coulomb_friction": ("stribeck_friction", "force"),  # the sliding level (static: beside)
    "viscous_damping": ("viscous_damping", "coefficient"),
    "mass_scale": ("mass_scale", "scale"),
    "actuator_gain": ("actuator_gain", "gain"),
    "actuator_deadzone": ("actuator_deadzone", "width"),
    "action_delay": ("action_delay", "steps"),
}


def truth_value(truth: dict, name: str, target: str):
    if name not in TRUTH_OF:
        return None
    effect, param = TRUTH_OF[name]
    for e in truth["effects"]:
        if e["name"] == effect and e["target"] == target:
            return e["params"][param]
    return None


def table(rows: list[dict]) -> str:
    """The README's table: per draw, what discovery named against the truth, what of the
    truth a library effect could have named and was not, and the held-out error."""
    lines = [
        "| draw | named: fit [95% interval] vs truth | in the library, not named (truth) "
        "| held-out NRMSE before -> after | unexplained |",
        "| --- | --- | --- | --- | --- |",
    ]
    for d in rows:
        values = d["truth"]["values"]
        named = []
        for e in d["named"]:
            ((param, x),) = e["params"].items()
            lo, hi = e["ci95"][param]
            truth = "none" if e["truth"] is None else f"{e['truth']:.3g}"
            if e["name"] == "coulomb_friction":
                static = values[f"stribeck_friction@{e['target']}.static"]
                truth += f" sliding, {static:.3g} static"
            named.append(f"{e['name']}@{e['target']} {x:.3g} [{lo:.3g}, {hi:.3g}] vs {truth}")
        keys = {f"{e['name']}@{e['target']}" for e in d["named"]}
        missed = []
        for key, x in values.items():
            effect, rest = key.split("@")
            target, param = rest.split(".")
            library = "coulomb_friction" if effect == "stribeck_friction" else effect
            if library not in TRUTH_OF or TRUTH_OF[library][1] != param:
                continue
            if f"{library}@{target}" in keys or (effect == "action_delay" and x == 0):
                continue
            missed.append(f"{library}@{target} {x:.3g}")
        before, after = d["nrmse_before"]["heldout"], d["nrmse_after"]["heldout"]
        lines.append(
            f"| {d['draw']} | {'; '.join(named) or 'nothing'} | {', '.join(missed)} "
            f"| {before:.3f} -> {after:.3f} | {d['unexplained_fraction']:.1%} |"
        )
    return "\n".join(lines)


def main(n_draws: int = 5) -> None:
    start = time.time()
    cfg0 = compose([*BASE, "real.draw=0"])
    env = make_env(cfg0.env)
    training = experiment.train_batch(cfg0, env, WORK / "round0", "pods_cl")
    params = training.params
    path = HERE / "results.json"
    rows = read_json(path)["draws"] if path.is_file() else []
    done = {r["draw"] for r in rows}
    for k in range(n_draws):
        if k in done:
            continue
        t0 = time.time()
        cfg = compose([*BASE, f"real.draw={k}"])
        truth = lab.draw("lab_cartpole", k)
        plant = make_plant(cfg.real, cfg.env)
        key = jax.random.split(jax.random.PRNGKey(cfg.seed + 7919))[1]  # the loop's round 1
        data, scale, notes = excite_until_identifiable(cfg, env, plant, params, key, [], cfg.env)
        data = concatenate(data)
        result = discover(data, cfg.env, cfg.discover)
        named = []
        for e in result.missing_effects:
            row = e.to_json()
            row["truth"] = truth_value(truth, e.name, e.target)
            named.append(row)
        heldout = {s: errs.normalized for s, (_, errs) in result.after.items()}
        before = {s: errs.normalized for s, (_, errs) in result.before.items()}
        rows.append(
            {
                "draw": k,
                "episodes": data.n_episodes,
                "excitation_scale": scale,
                "notes": notes,
                "named": named,
                "tentative": [e.to_json() for e in result.tentative],
                "law_mismatch": [e.to_json() for e in result.law_mismatch],
                "unexplained_fraction": result.unexplained_fraction,
                "nrmse_before": before,
                "nrmse_after": heldout,
                "warnings": result.warnings,
                "truth": truth,
                "seconds": time.time() - t0,
            }
        )
        atomic_write_json(path, {"draws": rows, "load_average": os.getloadavg()})
        print(
            f"draw {k}: {[e['name'] + '@' + e['target'] for e in named]} "
            f"unexplained {result.unexplained_fraction:.3f} ({time.time() - t0:.0f} s)"
        )
    print(f"total {time.time() - start:.0f} s")
    print(table(rows))


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 5)
