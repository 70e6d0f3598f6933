"""Issue 38.2, one measurement: what gap discovery names on lab_cartpole (or lab_furuta)
draws, against each draw's truth, and the held-out error it leaves unexplained.

The data are a sim2real loop's first round (hds.loop.record, excite_until_identifiable): a
balance policy trained by closed-loop PODS on the nominal simulator (round 0, the same for
every draw), deployed on the draw's plant, plus open-loop excitation, raised while the data
cannot identify what more excitation would. Discovery runs with its default candidates and
`breakaway_friction` (dry friction with a Stribeck peak), which it tries only as a refinement
of a named Coulomb friction. Writes experiments/lab_plants/results.json (results_furuta.json
with --furuta: the Furuta pendulum, env=furuta_balance).

    PYTHONPATH=$PWD .venv/bin/python experiments/lab_plants/measure.py [draws=5] [--fresh]
        [--furuta]

Per draw: what discovery named against the truth; whether a named library effect has an
interval that excludes no effect where the truth has none (the issue's proxy for an
out-of-library effect or a law mismatch, target: never); whether the truth is in the
interval and within 10% (masses, gains) or 25% (frictions: a Coulomb fit against the
sliding level, a breakaway friction's sliding and static levels each against the truth's) of
the fit;
and the held-out error the corrected model leaves (`remainder_fraction`, of which
`noise_fraction` is the measurement noise's). --fresh measures every draw again (results
of an earlier discovery are dropped; round 0's policy is kept).
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
from hds.effects.library import default_candidates
from hds.envs import make_env
from hds.loop import excite_until_identifiable
from hds.real import lab, make_plant
from hds.utils.io import atomic_write_json, read_json

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from rigid import RIGID  # noqa: E402

# discovery's candidates: its defaults and the dry friction with a Stribeck peak, which it
# tries only as a refinement of a named Coulomb friction (hds.discover.explain._refine)
EFFECTS = [*default_candidates(), "breakaway_friction"]
FAMILIES = {  # family: (its overrides, the results file)
    "lab_cartpole": (["real=lab_cartpole", "env.backend=analytic"], "results.json"),
    "lab_furuta": (["env=furuta_balance", "real=lab_furuta"], "results_furuta.json"),
}
COMMON = ["method=pods_cl", "logger=none"]
COMMON += ["discover.effects=[" + ",".join(EFFECTS) + "]"]

# what the truth holds for each library effect's parameter discovery may name
# ({effect: {param: (truth's effect, truth's param)}}); a dry friction's static level is
# judged against the truth's static level (a Coulomb fit's against the sliding level)
TRUTH_OF = {
    "coulomb_friction": {"force": ("stribeck_friction", "force")},
    "breakaway_friction": {
        "force": ("stribeck_friction", "force"),
        "static": ("stribeck_friction", "static"),
        "velocity": ("stribeck_friction", "velocity"),
    },
    "viscous_damping": {"coefficient": ("viscous_damping", "coefficient")},
    "mass_scale": {"scale": ("mass_scale", "scale")},
    "com_scale": {"scale": ("com_scale", "scale")},
    "inertia_scale": {"scale": ("inertia_scale", "scale")},
    "actuator_gain": {"gain": ("actuator_gain", "gain")},
    "actuator_deadzone": {"width": ("actuator_deadzone", "width")},
    "action_delay": {"steps": ("action_delay", "steps")},
}
FRICTION = 0.25  # the tolerance for frictions (and dead bands); 10% masses and gains
TOLERANCE = {"coulomb_friction": FRICTION, "breakaway_friction": FRICTION}
TOLERANCE |= {"viscous_damping": FRICTION, "actuator_deadzone": FRICTION}
TOLERANCE |= {name: 0.10 for name in RIGID}  # the rigid body's and the motor's scales
JUDGED = {"breakaway_friction": ("force", "static")}  # not the Stribeck velocity: no tolerance
NO_OP = {"action_delay": 0}  # a drawn value that is no effect


def truth_values(truth: dict, name: str, target: str) -> dict | None:
    """{param: the truth's value} of a named library effect, None where the truth has none."""
    if name not in TRUTH_OF:
        return None
    out = {}
    for param, (effect, theirs) in TRUTH_OF[name].items():
        for e in truth["effects"]:
            if e["name"] == effect and e["target"] == target:
                out[param] = e["params"][theirs]
    if not out or any(NO_OP.get(name) == v for v in out.values()):
        return None
    return out


def quantities(e: dict) -> dict:
    """{quantity: (fit, lo, hi)} of a named effect; a breakaway friction's static level is
    force + peak (its interval the sum of the two's ends: a bound)."""
    out = {p: (x, *e["ci95"][p]) for p, x in e["params"].items()}
    if e["name"] == "breakaway_friction":
        (f, flo, fhi), (p, plo, phi) = out.pop("force"), out.pop("peak")
        out = {"force": (f, flo, fhi), "static": (f + p, flo + plo, fhi + phi), **out}
    return out


def judge(e: dict) -> dict:
    """A named effect against the truth, per judged quantity: `spurious` (the truth has none
    and the interval excludes no effect), `covers` (the truth in the interval), `close`
    (within the issue's tolerance of the truth)."""
    values = quantities(e)
    judged = JUDGED.get(e["name"], tuple(values)[:1])
    nominal = 1.0 if e["name"] in RIGID else 0.0  # a scale: no effect at 1
    truth = e["truth"]
    if truth is None:
        x, lo, hi = values[judged[0]]
        return {judged[0]: {"spurious": not lo <= nominal <= hi, "covers": None, "close": None}}
    tol = TOLERANCE.get(e["name"])
    out = {}
    for q in judged:
        x, lo, hi = values[q]
        out[q] = {
            "spurious": False,
            "covers": bool(lo <= truth[q] <= hi),
            "close": None if tol is None else bool(abs(x - truth[q]) <= tol * abs(truth[q])),
        }
    return out


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def describe(e: dict, values: dict) -> str:
    """One named effect: each quantity's fit [interval] against the truth, and the verdicts."""
    verdict = judge(e)
    parts = []
    for q, (x, lo, hi) in quantities(e).items():
        if e["truth"] is None:
            truth = "none"
        elif e["name"] == "coulomb_friction":  # one level for two: both shown
            static = values[f"stribeck_friction@{e['target']}.static"]
            truth = f"{_fmt(e['truth'][q])} sliding, {_fmt(static)} static"
        else:
            truth = _fmt(e["truth"][q]) if q in e["truth"] else "?"
        v = verdict.get(q, {})
        mark = " **(spurious)**" if v.get("spurious") else ""
        mark += " (outside the tolerance)" if v.get("close") is False else ""
        mark += " (truth outside)" if v.get("covers") is False else ""
        label = "" if len(e["params"]) == 1 else f"{q} "
        parts.append(f"{label}{_fmt(x)} [{_fmt(lo)}, {_fmt(hi)}] vs {truth}{mark}")
    return f"{e['name']}@{e['target']} " + ", ".join(parts)


def totals(rows: list[dict]) -> dict:
    """Counts over the draws: effects named, spurious, truth covered, within the tolerance
    (frictions apart from masses and gains)."""
    named = [e for d in rows for e in d["named"]]
    verdicts = [(e, q, v) for e in named for q, v in judge(e).items()]
    friction = [
        v["close"]
        for e, _, v in verdicts
        if v["close"] is not None
        and e["name"] in ("coulomb_friction", "breakaway_friction", "viscous_damping")
    ]
    return {
        "named": len(named),
        "spurious": sum(v["spurious"] for _, _, v in verdicts),
        "covered": [v["covers"] for _, _, v in verdicts if v["covers"] is not None],
        "close": [v["close"] for _, _, v in verdicts if v["close"] is not None],
        "close_friction": friction,
    }


def table(rows: list[dict]) -> str:
    """The README's table: per draw, what discovery named against the truth, what of the
    truth a library effect could have named and was not, and the held-out error."""
    lines = [
        "| draw | named: fit [95% interval] vs truth | in the library, not named (truth) "
        "| held-out NRMSE before -> named -> with terms | unexplained by the named | "
        "left by the corrected model (noise) |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for d in rows:
        values = d["truth"]["values"]
        named = [describe(e, values) for e in d["named"]]
        keys = {f"{e['name']}@{e['target']}" for e in d["named"]}
        dry = {k.split("@")[1] for k in keys if k.split("@")[0] in TOLERANCE and "friction" in k}
        missed = []
        for key, x in values.items():
            effect, rest = key.split("@")
            target, param = rest.split(".")
            if effect == "stribeck_friction":
                if param == "force" and target not in dry:
                    missed.append(f"dry friction@{target} {_fmt(x)}")
                continue
            if effect not in TRUTH_OF or param not in TRUTH_OF[effect]:
                continue
            if f"{effect}@{target}" in keys or (effect == "action_delay" and x == 0):
                continue
            missed.append(f"{effect}@{target} {_fmt(x)}")
        before, after = d["nrmse_before"]["heldout"], d["nrmse_after"]["heldout"]
        terms = d.get("nrmse_with_terms", {}).get("heldout")
        errors = f"{before:.3f} -> {after:.3f}" + (f" -> {terms:.3f}" if terms else "")
        lines.append(
            f"| {d['draw']} | {'; '.join(named) or 'nothing'} | {', '.join(missed)} "
            f"| {errors} | {d['unexplained_fraction']:.1%} "
            f"| {d['remainder_fraction']:.1%} ({d['noise_fraction']:.1%}) |"
        )
    t = totals(rows)
    lines += [
        "",
        f"Over {len(rows)} draws: {t['named']} library effects named; {t['spurious']} with an "
        "interval that excludes no effect where the truth has none; the truth inside the "
        f"interval {sum(t['covered'])} of {len(t['covered'])} times; within the tolerance "
        f"(10% masses and gains, 25% frictions and dead bands) {sum(t['close'])} of "
        f"{len(t['close'])} times, frictions {sum(t['close_friction'])} of "
        f"{len(t['close_friction'])} (a breakaway friction's sliding and static levels each "
        "judged).",
    ]
    return "\n".join(lines)


def main(family: str, n_draws: int = 5, fresh: bool = False) -> None:
    start = time.time()
    overrides, results = FAMILIES[family]
    base = [*overrides, *COMMON]
    cfg0 = compose([*base, "real.draw=0"])
    env = make_env(cfg0.env)
    work = Path("outputs/lab_plants") / family  # round 0's checkpoints (resumable)
    training = experiment.train_batch(cfg0, env, work / "round0", "pods_cl")
    params = training.params
    path = HERE / results
    rows = read_json(path)["draws"] if path.is_file() and not fresh else []
    done = {r["draw"] for r in rows}
    for k in range(n_draws):
        if k in done:
            continue
        t0, c0 = time.time(), time.process_time()
        cfg = compose([*base, f"real.draw={k}"])
        truth = lab.draw(family, k)
        plant = make_plant(cfg.real, cfg.env)
        key = jax.random.split(jax.random.PRNGKey(cfg.seed + 7919))[1]  # the loop's round 1
        data, scale, notes = excite_until_identifiable(cfg, env, plant, params, key, [], cfg.env)
        data = concatenate(data)
        result = discover(data, cfg.env, cfg.discover)
        named = []
        for e in result.missing_effects:
            row = e.to_json()
            row["truth"] = truth_values(truth, e.name, e.target)
            named.append(row)
        heldout = {s: errs.normalized for s, (_, errs) in result.after.items()}
        with_terms = {s: errs.normalized for s, (_, errs) in result.after_terms.items()}
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
                "dropped": result.to_json().get("dropped_proxies", []),
                "unexplained_fraction": result.unexplained_fraction,
                "remainder_fraction": result.remainder_fraction,
                "noise_fraction": result.noise_fraction,
                "terms": [t.describe() for t in result.terms],
                "nrmse_before": before,
                "nrmse_after": heldout,
                "nrmse_with_terms": with_terms,
                "warnings": result.warnings,
                "truth": truth,
                "seconds": time.time() - t0,
                "cpu_seconds": time.process_time() - c0,
            }
        )
        atomic_write_json(path, {"draws": rows, "load_average": os.getloadavg()})
        print(
            f"draw {k}: {[e['name'] + '@' + e['target'] for e in named]} "
            f"unexplained {result.unexplained_fraction:.3f} remainder "
            f"{result.remainder_fraction:.3f} ({time.time() - t0:.0f} s, "
            f"{time.process_time() - c0:.0f} CPU s)",
            flush=True,
        )
    print(f"total {time.time() - start:.0f} s")
    print(table(sorted(rows, key=lambda r: r["draw"])))


if __name__ == "__main__":
    numbers = [a for a in sys.argv[1:] if not a.startswith("--")]
    chosen = "lab_furuta" if "--furuta" in sys.argv else "lab_cartpole"
    main(chosen, int(numbers[0]) if numbers else 5, "--fresh" in sys.argv)
