"""`python -m experiments.excitation_design.bound [--cases friction80 friction_gain]`: the most
any open-loop excitation within the issue's limits (the amplitude bound, the rail's ends, the
same record length) is found to carry about the targeted parameters, on the model (the fit's
simulator at the true values, the true sensor noise): every step's control a free variable
(`Designer.per_step`: projected Adam on the case's asked-width criterion, 200 iterations, from
each standard signal, the best 2 ceiling signals within the rail and 2 random starts), against
the best standard signal of the experiment (random steps, PRBS with a bit every 4 steps, chirp;
16 draws). Prints a markdown table of the predicted plant time to the target and writes the
per-step controls to bound.json (`python -m experiments.excitation_design --per-step` plays
them on the plants: designed at the true values, an oracle, it shows what the plants' records
give of the model's bound).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from omegaconf import OmegaConf
from scipy import stats

from experiments.excitation_design.__main__ import (
    CASES,
    CONF,
    HERE,
    ROUNDS,
    SIGNALS,
    NoisyPlant,
    anchored_time,
    case_plant,
    worst,
)
from experiments.excitation_design.ceiling import EPISODES, setup, signals
from hds.config import env_config
from hds.data import collect
from hds.discover.design import WindowFit
from hds.discover.workflow import fit_backend, with_backend
from hds.utils.io import atomic_write_json
from hds.utils.runtime import enable_compilation_cache

STANDARD = {"steps": "random steps", "prbs": "PRBS, bit 4 steps", "chirp": "chirp"}


def bound_case(name, iterations=200, restarts=2, best_starts=2, at=None, noise=None):
    """The per-step search of a case at `at` ({key: {param: value}}, default the true values)
    with sensor noise `noise` (default the true): the starts are ranked and the search is
    run there; the times reported are at the true values."""
    spec = CASES[name]
    env, designer, limits, x0, truth, values = setup(name)
    at = truth if at is None else at
    noise = spec["noise"] if noise is None else noise
    steps, dt = int(env.task.horizon), float(env.sim.dt)
    t_q = stats.t.ppf(0.975, EPISODES - 1) / np.sqrt(EPISODES)

    def time_of(se):  # plant time to the target in units of 16 episodes: (width / target)^2
        return worst(values, t_q * se, designer.labels, spec["targets"]) ** 2

    times, ranks, within = {}, {}, {}
    for label, u in signals(env, steps, dt, limits.u_high[0]).items():
        times[label] = time_of(designer.predicted_se_of(truth, u, x0, spec["noise"]))
        ranks[label] = time_of(designer.predicted_se_of(at, u, x0, noise))
        if max(limits.violation(designer.open_loop(at, u[0], x0), u[0]).values()) <= 0:
            within[label] = u[0]
    # the standard signals and the best `best_starts` others within the rail as starts
    others = sorted((k for k in within if k not in STANDARD.values()), key=ranks.get)
    starts = {k: within[k] for k in [*STANDARD.values(), *others[:best_starts]] if k in within}
    t0 = time.time()
    best = designer.per_step(
        at,
        x0,
        noise,
        limits,
        criterion=spec["targets"],
        iterations=iterations,
        restarts=restarts,
        starts=starts,
    )
    wall = time.time() - t0
    bound = time_of(designer.predicted_se_of(truth, best["controls"][None], x0, spec["noise"]))
    standard = min(times[v] for v in STANDARD.values())
    best_start = min(times[k] for k in starts)
    return {
        "case": name,
        "bound": bound,
        "standard": standard,
        "best_start": best_start,
        "start": best["start"],
        "wall": wall,
        "switches": int(np.sum(np.abs(np.diff(np.sign(best["controls"][:, 0]))) > 0)),
        "controls": best["controls"].tolist(),
        "at_bound": float(np.mean(np.isclose(np.abs(best["controls"]), limits.u_high, rtol=1e-3))),
    }


def play(name, controls, repeats=5):
    """`controls` [T, n_act], or a list of them, one per repeat."""
    """The plant's records of the per-step controls repeated 16 times, fitted as the
    experiment fits (the same plant noise seeds per repeat): the plant seconds to the target
    by 1/sqrt(time) through the width at 16 episodes, per repeat, noise part and reported."""
    spec = CASES[name]
    env, designer, _, x0, _, _ = setup(name)
    env_cfg = env_config(
        OmegaConf.to_container(OmegaConf.load(CONF / "env" / f"{spec['env']}.yaml"))
    )
    fit_cfg = with_backend(env_cfg, fit_backend(env_cfg, "auto"))
    plant_base = case_plant(spec, env_cfg, fit_cfg)
    fitter = WindowFit(designer, sum(ROUNDS))
    start = np.array(designer.model.start, np.float64)
    theta0 = designer.theta(None)
    theta0[designer.slots] = start[designer.slots]
    n = sum(ROUNDS)
    per_repeat = np.asarray(controls, np.float64)
    if per_repeat.ndim == 2:
        per_repeat = np.repeat(per_repeat[None], repeats, axis=0)
    q0 = np.tile(x0[: env.sim.nq], (n, 1))
    qd0 = np.zeros((n, env.sim.n_obs - env.sim.nq))
    seconds = n * int(env.task.horizon) * float(env.sim.dt)
    out = {"ratio": [], "ratio_reported": []}
    for rep in range(repeats):
        plant = NoisyPlant(plant_base, spec["noise"], 1000 + rep)
        u = np.repeat(per_repeat[rep][None], n, axis=0)
        ds = collect(plant, env.task, q0, qd0, u)
        fit = fitter(ds.obs, ds.actions, theta0)
        labels, targets = designer.labels, spec["targets"]
        out["ratio"].append(seconds * worst(fit["values"], fit["noise_half"], labels, targets) ** 2)
        out["ratio_reported"].append(
            seconds * worst(fit["values"], fit["half"], labels, targets) ** 2
        )
    return out


def round1_controls(name, stored, repeats, iterations):
    """Per repeat: the per-step search at the designed arm's estimate and measured noise after
    its first 4 episodes (results.json), what a sequential design knows then; not the truth."""
    spec, out = CASES[name], []
    for rep in range(repeats):
        row = next(
            r for r in stored[name]["rows"] if r["signal"] == "designed" and r["repeat"] == rep
        )
        at = {}
        for label, v in zip(stored[name]["labels"], row["values"][1], strict=True):
            key, p = label.rsplit(".", 1)
            at.setdefault(key, {})[p] = float(v)
        noise = np.asarray(row["noise_estimate_over_true"][1]) * np.asarray(spec["noise"])
        r = bound_case(name, iterations, 1, 1, at=at, noise=noise)
        print(f"{name} rep {rep}: at {at}, model bound ratio {r['standard'] / r['bound']:.2f}")
        out.append(r["controls"])
    return out


def plant_table(cases, repeats=5, round1=False, iterations=100):
    """Markdown: the per-step signal's plant time on the plants against the best standard
    signal's in results.json (the same protocol and noise seeds); the per-step signal found
    at the true values (bound.json, an oracle), or with `round1` at the designed arm's
    estimate after 4 episodes, per repeat."""
    bound = json.loads((HERE / "bound.json").read_text())
    stored = json.loads((HERE / "results.json").read_text())["cases"]
    lines = [
        "| case | interval part | per-step plant s to target: median [min, max] | best "
        "standard's (signal) | best standard's / per-step's | designed's / per-step's |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for name in cases:
        # the control plant has the model's laws at the same true values: the same bound
        source = "friction80" if name == "friction80_own_laws" else name
        if round1:
            controls = round1_controls(name, stored, repeats, iterations)
        else:
            controls = bound[source]["controls"]
        times = play(name, controls, repeats)
        for key, what in (("ratio", "noise"), ("ratio_reported", "reported")):
            t = np.array(times[key])
            by = {
                s: float(
                    np.median(
                        [anchored_time(r, key) for r in stored[name]["rows"] if r["signal"] == s]
                    )
                )
                for s in SIGNALS
            }
            best = min((s for s in SIGNALS if s != "designed"), key=by.get)
            lines.append(
                f"| {name} | {what} | {np.median(t):.3g} [{t.min():.3g}, {t.max():.3g}] | "
                f"{by[best]:.3g} ({best}) | {by[best] / np.median(t):.2f} | "
                f"{by['designed'] / np.median(t):.2f} |"
            )
            print(lines[-1], flush=True)
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=["friction80", "friction_gain"])
    ap.add_argument("--iterations", type=int, default=200)
    ap.add_argument("--restarts", type=int, default=2)
    ap.add_argument("--best-starts", type=int, default=2)
    ap.add_argument(
        "--plant", action="store_true", help="play bound.json's controls on the plants instead"
    )
    ap.add_argument(
        "--round1",
        action="store_true",
        help="with --plant: search per repeat at the designed arm's estimate after 4 episodes",
    )
    args = ap.parse_args(argv)
    enable_compilation_cache()
    if args.plant:
        print(plant_table(args.cases, round1=args.round1, iterations=args.iterations))
        return
    results = {}
    lines = [
        "| case | best standard's predicted plant time / per-step's | best start's / per-step's "
        "| winning start | sign changes | share of steps at the bound | wall s |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name in args.cases:
        r = bound_case(name, args.iterations, args.restarts, args.best_starts)
        lines.append(
            f"| {name} | {r['standard'] / r['bound']:.2f} | {r['best_start'] / r['bound']:.2f} "
            f"| {r['start']} | {r['switches']} | {r['at_bound']:.2f} | {r['wall']:.0f} |"
        )
        print(lines[-1], flush=True)
        results[name] = r
    print("\n".join(lines))
    path = HERE / "bound.json"
    old = json.loads(path.read_text()) if path.exists() else {}
    atomic_write_json(path, {**old, **results})


if __name__ == "__main__":
    main()
