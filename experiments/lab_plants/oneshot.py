"""Issue 38, the one-shot corrected simulator's discovery on lab cart-pole draws, alone: the
data `method=pods_corrected` records on each draw's plant (`hds.simulators.discovery_data`:
the lab study's 64 excitation episodes of random steps), then `hds.discover.discover` on them,
judged against the draw's truth as measure.py judges the loop's data. No training.

    PYTHONPATH=$PWD .venv/bin/python experiments/lab_plants/oneshot.py 0 1 2 3 4 [--label L]

Each draw's data are kept in outputs/lab_plants/oneshot/dK.npz (recorded once: discovery is
rerun on the same data), its result in experiments/lab_plants/oneshot.json under the label
(default `now`), so two code versions' results stand side by side. `--table L1 L2`
prints the README's tables of labels L1 and L2.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from hds.config import compose
from hds.data import load, save
from hds.discover import discover
from hds.envs import make_env
from hds.real import lab, make_plant
from hds.simulators import discovery_data
from hds.utils.io import atomic_write_json, read_json

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from measure import judge, truth_values  # noqa: E402

STUDY = [
    "+experiment=[lab_study,lab_task_cartpole_balance]",
    "method=pods_corrected",
    "logger=none",
    "hydra.mode=RUN",
]
DATA = Path("outputs/lab_plants/oneshot")


def one(k: int) -> dict:
    cfg = compose([*STUDY, f"real.draw={k}"], config_dirs=["experiments/lab_study/conf"])
    env = make_env(cfg.env)
    path = DATA / f"d{k}.npz"
    if not path.is_file():
        plant = make_plant(cfg.real, cfg.env)
        data, _ = discovery_data(cfg, env, plant)
        save(data, path)
    data = load(path)
    t0, c0 = time.time(), time.process_time()
    result = discover(data, cfg.env, cfg.discover)
    truth = lab.draw("lab_cartpole", k)
    named = []
    for e in result.missing_effects:
        row = e.to_json()
        row["truth"] = truth_values(truth, e.name, e.target)
        row["verdict"] = judge(row)
        named.append(row)
    return {
        "draw": k,
        "episodes": data.n_episodes,
        "named": named,
        "law_mismatch": [e.to_json() for e in result.law_mismatch],
        "unexplained_fraction": result.unexplained_fraction,
        "warnings": result.warnings,
        "truth": truth,
        "seconds": time.time() - t0,
        "cpu_seconds": time.process_time() - c0,
        "load_average": os.getloadavg(),
    }


def _named(row: dict) -> str:
    parts = []
    for e in row["named"]:
        ((q, x),) = list(e["params"].items())[:1]
        lo, hi = e["ci95"][q]
        truth = "none" if e["truth"] is None else f"{e['truth'][q]:.3g}"
        mark = " **spurious**" if e["verdict"][q]["spurious"] else ""
        mark += " (truth outside)" if e["verdict"][q]["covers"] is False else ""
        parts.append(f"{e['name']} {x:.3g} [{lo:.3g}, {hi:.3g}] vs {truth}{mark}")
    return "; ".join(parts) or "nothing"


def table(results: dict, labels: list[str]) -> str:
    """Per draw, each label's named effects against the truth; then per label: the draws
    with a spurious name, the delays named of those the plant has, the rail frictions
    within 25% of the Stribeck sliding level, the truth inside the intervals."""
    draws = sorted({int(k) for lab in labels for k in results[lab]})
    lines = ["| draw | delay | " + " | ".join(labels) + " |", "|---" * (len(labels) + 2) + "|"]
    for k in draws:
        delay = lab_delay(results[labels[0]][str(k)])
        cells = [_named(results[lab][str(k)]) for lab in labels]
        lines.append(f"| {k} | {delay} | " + " | ".join(cells) + " |")
    lines += ["", "| | " + " | ".join(labels) + " |", "|---" * (len(labels) + 1) + "|"]
    stats = {lab: counts([results[lab][str(k)] for k in draws]) for lab in labels}
    for what in stats[labels[0]]:
        lines.append(f"| {what} | " + " | ".join(stats[lab][what] for lab in labels) + " |")
    return "\n".join(lines)


def lab_delay(row: dict) -> int:
    return int(row["truth"]["values"]["action_delay@slide.steps"])


def counts(rows: list[dict]) -> dict:
    n = len(rows)
    spurious = [
        r for r in rows if any(v["spurious"] for e in r["named"] for v in e["verdict"].values())
    ]
    with_delay = [r for r in rows if lab_delay(r)]
    delay_named = [
        r
        for r in with_delay
        if any(
            e["name"] == "action_delay" and e["params"]["steps"] == lab_delay(r) for e in r["named"]
        )
    ]
    frictions = [
        e
        for r in rows
        for e in r["named"]
        if e["name"] == "coulomb_friction" and e["target"] == "slider"
    ]
    close = [e for e in frictions if e["verdict"]["force"]["close"]]
    covered = [
        v["covers"]
        for r in rows
        for e in r["named"]
        for v in e["verdict"].values()
        if v["covers"] is not None
    ]
    return {
        "draws with a spurious name": f"{len(spurious)} of {n}",
        "the delay named (its length) where the plant has one": (
            f"{len(delay_named)} of {len(with_delay)}"
        ),
        "rail friction within 25% of the sliding level": f"{len(close)} of {len(frictions)}",
        "truth inside the interval": f"{sum(covered)} of {len(covered)}",
    }


def main(draws: list[int], label: str) -> None:
    out = HERE / "oneshot.json"
    results = read_json(out) if out.is_file() else {}
    for k in draws:
        row = one(k)
        results.setdefault(label, {})[str(k)] = row
        atomic_write_json(out, results)
        said = [
            f"{e['name']}@{e['target']} {e['params']} {e['ci95']} truth {e['truth']} {e['verdict']}"
            for e in row["named"]
        ]
        print(f"draw {k} ({row['cpu_seconds']:.0f} CPU s):", *said, sep="\n  ", flush=True)


if __name__ == "__main__":
    args = sys.argv[1:]
    if "--table" in args:  # --table LABEL [LABEL ...]: the README's tables
        print(table(read_json(HERE / "oneshot.json"), args[args.index("--table") + 1 :]))
        sys.exit()
    label = args[args.index("--label") + 1] if "--label" in args else "now"
    picked = [int(a) for a in args if a.isdigit()]
    main(picked, label)
