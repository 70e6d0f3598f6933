"""The lab study's tables (issue 38.4; `make study-lab`'s last step): per task and draw, each
method's real cost over the oracle's, with a 95% interval over seeds, the plant time its data
cost, what discovery named against the draw's truth, the held-out error it left
unexplained and the share of the draw's rigid-body and motor error its model leaves
(experiments/lab_plants/rigid.py); then per method over the draws: the mean ratio, the
share of draws within 1.05 of the oracle, and the plant time each needed to get there.

    PYTHONPATH=$PWD .venv/bin/python experiments/lab_study/report.py [outputs/study/lab]

Reads what the study's runs wrote (outputs/study/lab/<task>/: per_draw/, shared/, loop/dK/,
hybrid/dK/) and writes <study dir>/report.md and report.json; prints the markdown. A cost is
minus a real return; a method's ratio on a draw is each seed's cost over the oracle's mean
cost on that draw (the interval is over the method's seeds, the oracle's mean taken as
exact), and over draws the interval is over every (draw, seed).
"""

from __future__ import annotations

import importlib.util
import math
import re
import sys
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from hds.gap import mean_ci
from hds.loop import improved, result_round
from hds.real import lab
from hds.results import PlantTime, Row, Summary
from hds.utils.io import atomic_write_json, read_json

HERE = Path(__file__).resolve().parent
METHODS = ("raw", "dr", "corrected", "loop", "hybrid", "loop_1", "hybrid_1", "oracle")
ABOUT = {
    "raw": "closed-loop PODS on the raw simulator",
    "dr": "domain randomization over the family's distribution",
    "corrected": "one-shot corrected simulator",
    "loop": "the loop (3 rounds)",
    "hybrid": "the loop with HDS's hybrid model",
    "loop_1": "the loop stopped after 1 round (a shorter run)",
    "hybrid_1": "the loop with the hybrid, stopped after 1 round",
    "oracle": "the oracle on the plant's replica",
}
WITHIN = 1.05  # the target: within 1.05 of the oracle's cost


def _module(name: str):
    """experiments/lab_plants/<name>.py as a module: measure (truth_values, what a draw's truth
    holds for a library effect discovery may name, per parameter; quantities, a named effect's
    judged quantities: a breakaway friction's static level is force + peak) and rigid (the
    rigid-body and motor error a named model leaves), one definition for both experiments."""
    spec = importlib.util.spec_from_file_location(
        f"lab_{name}", HERE.parent / "lab_plants" / f"{name}.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


_MEASURE, _RIGID = _module("measure"), _module("rigid")
truth_values = _MEASURE.truth_values


def family_of(task: str) -> str:
    """The lab family (hds.real.lab) of a study task: furuta_* or cart-pole."""
    return "lab_furuta" if task.startswith("furuta") else "lab_cartpole"


def study_experiment(task: str) -> str:
    """The override that composes a task's per-draw study configs, as `make study-lab` does."""
    suffix = "_furuta" if family_of(task) == "lab_furuta" else ""
    return f"+experiment=[lab_study{suffix},lab_task_{task}]"


def draw_of(plant: str) -> int | None:
    match = re.search(r"#(\d+)$", plant or "")
    return int(match.group(1)) if match else None


def kind_of(method: str) -> str:
    if method == "oracle":
        return "oracle"
    if "corrected" in method:
        return "corrected"
    if "dr" in method.split("+") or "randomized" in method:
        return "dr"
    return "raw"


def config_of(run_dir: Path):
    for path in (run_dir / "config.yaml", run_dir / ".hydra" / "config.yaml"):
        if path.is_file():
            return OmegaConf.load(path)
    return None


def _g(x: float) -> str:
    """A value to 3 significant digits; "-" where there is none (no interval, no truth)."""
    return "-" if math.isnan(x) else f"{x:.3g}"


def named_vs_truth(effects: list[dict], truth: dict) -> str:
    """Each named effect's fit [95% interval] against the draw's truth; an effect of several
    quantities names each (a breakaway friction's sliding and static levels and velocity)."""
    parts = []
    for e in effects:
        values = truth_values(truth, e["name"], e["target"])
        nan = (float("nan"), float("nan"))
        cis = {p: e.get("ci95", {}).get(p, nan) for p in e["params"]}
        fits = _MEASURE.quantities({**e, "ci95": cis})
        items = []
        for q, (x, lo, hi) in fits.items():
            true = "not in the plant" if values is None else _g(values.get(q, float("nan")))
            label = f"{q} " if len(fits) > 1 else ""
            items.append(f"{label}{_g(x)} [{_g(lo)}, {_g(hi)}] vs {true}")
        parts.append(f"{e['name']}@{e['target']} " + ", ".join(items))
    return "; ".join(parts) or "nothing"


def rigid_left(truth: dict, named: list[dict]) -> str:
    """Per joint, the share of the nominal's rigid-body and motor error (the acceleration it
    predicts) the named effects leave (experiments/lab_plants/rigid.py): 0 the truth's, 1 the
    nominal's."""
    left = _RIGID.error_left(truth["xml"], truth["effects"], named)
    return ", ".join(f"{joint} {x:.2f}" for joint, x in left.items())


def unexplained(discovery_dir: Path) -> float | None:
    path = discovery_dir / "report.json"
    return read_json(path).get("unexplained_fraction") if path.is_file() else None


def gather(task_dir: Path) -> dict:
    """{draw: {method: {costs: [per seed], plant_s, named, unexplained, rounds}}}."""
    out: dict[int, dict] = {}

    def put(draw, method, **fields):
        out.setdefault(draw, {})[method] = fields

    for path in sorted((task_dir / "per_draw").glob("*/summary.json")):
        summary, run_dir = Summary.read(path), path.parent
        for method in {r.method for r in summary.rows}:
            rows = [r for r in summary.rows if r.method == method]
            draw, kind = draw_of(rows[0].plant), kind_of(method)
            fields = {"costs": [-r.real_return for r in rows], "solved_sim": _solved(rows)}
            if kind == "corrected":
                cfg = config_of(run_dir)
                dt = cfg.env.timestep * cfg.env.frames_per_step
                episodes = summary.discovery.get("episodes", 0)
                fields["plant_s"] = PlantTime(0.0, episodes * cfg.dynamics.horizon * dt).total_s
                fields["named"] = summary.discovery.get("effects", [])
                fields["unexplained"] = unexplained(run_dir / "discovery")
            put(draw, kind, **fields)
    for path in sorted((task_dir / "shared").glob("*/summary.json")):
        summary = Summary.read(path)
        for row_set in (summary.rows, summary.rows_eval_plants):
            for method in {r.method for r in row_set}:
                by_draw: dict[int, list[Row]] = {}
                for r in row_set:
                    if r.method == method:
                        by_draw.setdefault(draw_of(r.plant), []).append(r)
                for draw, rows in by_draw.items():
                    costs = [-r.real_return for r in rows]
                    put(draw, kind_of(method), costs=costs, plant_s=0.0, solved_sim=_solved(rows))
    for kind in ("loop", "hybrid"):
        for loop_dir in sorted((task_dir / kind).glob("d*")):
            rounds, draw = loop_rounds(loop_dir), int(loop_dir.name[1:])
            if not rounds:
                continue
            per_round = [
                {
                    "cost": float(np.mean([-Row.from_json(r).real_return for r in x["rows"]])),
                    "plant_s": PlantTime.from_json(x.get("plant_time_so_far")).total_s,
                    "model_used": (x.get("model") or {}).get("used"),
                    "multistep": (x.get("model") or {}).get("multistep"),
                }
                for x in rounds
            ]
            last = rounds[result_round(rounds)]  # the round whose policies the loop leaves
            rows = [Row.from_json(r) for r in last["rows"]]
            put(
                draw,
                kind,
                costs=[-r.real_return for r in rows],
                solved_sim=_solved(rows),
                plant_s=per_round[-1]["plant_s"],
                named=last["effects"],
                unexplained=unexplained(loop_dir / "rounds" / str(last["round"]) / "discovery"),
                rounds=per_round,
            )
    return out


def loop_rounds(loop_dir: Path) -> list[dict]:
    """A loop's rounds: loop.json's when it ended; else each finished round's round.json, its
    named effects from its discovery report and its plant time from its recorded data (what
    the loop reports; rounds written before round.json held them)."""
    if (loop_dir / "loop.json").is_file():
        return read_json(loop_dir / "loop.json")["rounds"]
    from hds.data import load

    cfg, rounds, spent = config_of(loop_dir), [], PlantTime()
    for r in range(cfg.loop.rounds + 1):
        rdir = loop_dir / "rounds" / str(r)
        if not (rdir / "round.json").is_file():
            break
        report = read_json(rdir / "round.json")
        if "plant_time_so_far" not in report:
            effects = []
            if r > 0:
                data = load(rdir / "data.npz")
                spent += PlantTime.of_round(
                    data.n_episodes,
                    data.horizon,
                    data.dt,
                    cfg.loop.deploy_episodes,
                    cfg.loop.excitation_episodes,
                )
                effects = read_json(rdir / "discovery" / "report.json")["missing_effects"]
            report |= {"round": r, "effects": effects, "plant_time_so_far": spent.to_json()}
        rounds.append(report)
    return rounds


def _solved(rows) -> float | None:
    flags = [r.solved_sim for r in rows if r.solved_sim is not None]
    return float(np.mean(flags)) if flags else None


def _num(x) -> str:
    return "-" if x is None else f"{x:.3g}"


def first_within(entry: dict, oracle_cost: float) -> float | None:
    """The plant time a method needed to reach WITHIN x the oracle's mean cost: a loop's first
    round that did (its data so far), another method's own data if it did; None: never."""
    if "rounds" in entry:
        for r in entry["rounds"]:
            if r["cost"] <= WITHIN * oracle_cost:
                return r["plant_s"]
        return None
    return entry.get("plant_s") if np.mean(entry["costs"]) <= WITHIN * oracle_cost else None


def tables(task: str, family: str, data: dict) -> tuple[str, dict]:
    lines = [f"### {task}", ""]
    header = (
        "| draw | method | cost / oracle's [95% over seeds] | solved on its simulator | "
        "plant s | named vs truth | unexplained | rigid body left |"
    )
    lines += [header, "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    ratios: dict[str, list[float]] = {m: [] for m in METHODS}
    within: dict[str, list[bool]] = {m: [] for m in METHODS}
    reach: dict[str, list] = {m: [] for m in METHODS}
    for draw in sorted(data):
        methods = data[draw]
        if "oracle" not in methods:
            continue
        oracle = float(np.mean(methods["oracle"]["costs"]))
        truth = lab.draw(family, draw)
        for m in METHODS:
            if m not in methods:
                continue
            e = methods[m]
            r = np.asarray(e["costs"]) / oracle
            ci = mean_ci(r)
            ratios[m] += r.tolist()
            within[m].append(ci[0] <= WITHIN)
            reach[m].append(first_within(e, oracle))
            solved = "-" if e.get("solved_sim") is None else f"{e['solved_sim']:.0%}"
            named = named_vs_truth(e["named"], truth) if "named" in e else ""
            share = e.get("unexplained")
            lines.append(
                f"| {draw} | {m} | {ci[0]:.3f} [{ci[1]:.3f}, {ci[2]:.3f}] | {solved} | "
                f"{e.get('plant_s', 0.0):.0f} | {named} | "
                f"{'' if share is None else f'{share:.1%}'} | "
                f"{rigid_left(truth, e['named']) if 'named' in e else ''} |"
            )
    lines += [
        "",
        f"Over the draws ({task}): the mean ratio with its 95% interval over every (draw, seed), "
        f"the draws whose mean is within {WITHIN} of the oracle's, and the plant time each "
        "method had used when it first got there (per draw; never: -).",
        "",
        "| method | cost / oracle's | draws within 1.05 | plant s to reach 1.05 |",
        "| --- | --- | --- | --- |",
    ]
    summary = {}
    for m in METHODS:
        if not ratios[m]:
            continue
        ci = mean_ci(ratios[m])
        times = ", ".join("-" if t is None else f"{t:.0f}" for t in reach[m])
        lines.append(
            f"| {m} ({ABOUT[m]}) | {ci[0]:.3f} [{ci[1]:.3f}, {ci[2]:.3f}] | "
            f"{sum(within[m])} of {len(within[m])} | {times} |"
        )
        summary[m] = {"ratio": list(ci), "within": within[m], "plant_s_to_reach": reach[m]}
    lines += room_for_a_model(data)
    hybrid = [
        (draw, i, r)
        for draw in sorted(data)
        for m in ("hybrid", "hybrid_1")
        for i, r in enumerate(data[draw].get(m, {}).get("rounds", []))
        if r.get("multistep")
    ]
    if hybrid:
        lines += [
            "",
            "HDS's hybrid per round: its open-loop NRMSE on the held-out episodes against the "
            "corrected simulator's (model / corrected simulator) at each k, and whether the "
            "round used it.",
            "",
            "| draw | round | "
            + " | ".join(f"k={k}" for k in hybrid[0][2]["multistep"])
            + " | used |",
            "| --- | --- | " + " | ".join("---" for _ in hybrid[0][2]["multistep"]) + " | --- |",
        ]
        for draw, i, r in hybrid:
            errors = " | ".join(
                f"{_num(row.get('model'))} / {_num(row.get('simulator'))}"
                for row in r["multistep"].values()
            )
            lines.append(f"| {draw} | {i} | {errors} | {'yes' if r['model_used'] else 'no'} |")
    return "\n".join(lines), {"draws": data, "summary": summary}


def beats(a: list[float], b: list[float]) -> bool:
    """Whether costs `a` are lower than `b` beyond their 95% intervals over seeds: the loop's
    rule for a round that improved (`hds.loop.improved`), on the returns -b then -a."""
    returns = lambda costs: {"real_return": mean_ci([-c for c in costs])}  # noqa: E731
    return improved(returns(b), returns(a))


def room_for_a_model(data: dict) -> list[str]:
    """The hybrid against the loop per draw, beside the room the loop leaves: a draw has room
    where the oracle beats the loop beyond the intervals (`beats`). Elsewhere the loop is at
    the oracle's level within the seeds' spread, and a model could beat it beyond the
    intervals only by beating the oracle, which trains on the plant's own replica."""
    rows, room, won = [], 0, 0
    for draw in sorted(data):
        methods = data[draw]
        if not {"oracle", "loop", "hybrid"} <= set(methods):
            continue
        oracle = float(np.mean(methods["oracle"]["costs"]))
        loop, hybrid, best = (
            (np.asarray(methods[m]["costs"]) / oracle).tolist()
            for m in ("loop", "hybrid", "oracle")
        )
        has_room, wins = beats(best, loop), beats(hybrid, loop)
        room, won = room + has_room, won + (has_room and wins)
        (lm, ll, lh), (hm, hl, hh) = mean_ci(loop), mean_ci(hybrid)
        rows.append(
            f"| {draw} | {lm:.3f} [{ll:.3f}, {lh:.3f}] | {'yes' if has_room else 'no'} | "
            f"{hm:.3f} [{hl:.3f}, {hh:.3f}] | {'yes' if wins else 'no'} |"
        )
    if not rows:
        return []
    return [
        "",
        "Room for a learned model: the loop's and the hybrid's cost over the oracle's per draw "
        "[95% over seeds]; a draw has room where the oracle beats the loop beyond both "
        "intervals (elsewhere only a model that beat the oracle could beat the loop beyond "
        "them); whether the hybrid beats the loop beyond both intervals. Draws with room: "
        f"{room} of {len(rows)}; the hybrid beats the loop on {won} of them.",
        "",
        "| draw | loop / oracle's | room | hybrid / oracle's | hybrid beats the loop |",
        "| --- | --- | --- | --- | --- |",
        *rows,
    ]


def main(study_dir: str = "outputs/study/lab", *one_round: str) -> None:
    """`one_round`: study directories of loops stopped after 1 round (loop.rounds=1), whose
    loops are reported beside the study's as loop_1 and hybrid_1."""
    study_dir = Path(study_dir)
    parts, everything = [], {}
    for task_dir in sorted(p for p in study_dir.iterdir() if p.is_dir()):
        family = family_of(task_dir.name)
        data = gather(task_dir)
        for other in one_round:
            for draw, methods in gather(Path(other) / task_dir.name).items():
                for m in ("loop", "hybrid"):
                    if m in methods:
                        data.setdefault(draw, {})[f"{m}_1"] = methods[m]
        if not data:
            continue
        text, everything[task_dir.name] = tables(task_dir.name, family, data)
        parts.append(text)
    markdown = "\n\n".join(parts) + "\n"
    (study_dir / "report.md").write_text(markdown)
    atomic_write_json(study_dir / "report.json", everything)
    print(markdown)


if __name__ == "__main__":
    main(*sys.argv[1:])
