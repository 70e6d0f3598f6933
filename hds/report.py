"""`python -m hds.report dir=DIR`: a markdown report of a run or a sweep directory.

It reads every summary.json below DIR (one per run or job) and writes, into DIR:
  report.md      a table of mean and 95% interval over seeds per method and friction gap, figures
  report.csv     one row per method, friction gap and seed, for people who plot their own
  plots/report_*.png
and, with gif=true, an animation of the same policy on the simulator and on the real plant (of
the run, or of a sweep's first job; gif=JOB: of that job; gif_plant=KEY: on one of its
eval_plants instead). out=DIR writes the report there instead (figures copied).
A gap-discovery run's report (report.json) is linked with its before/after errors and figures;
DIR may also be a `python -m hds.discover` output directory alone, whose report then goes to
DIR/report/ (discovery's own report.md stays as it is).
"""

from __future__ import annotations

import csv
import io
import os
from collections import defaultdict
from dataclasses import replace
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from hds import plots, story
from hds.animate import animate_episodes
from hds.config import load_config
from hds.effects.apply import applied
from hds.gap import mean_ci
from hds.results import Row, Summary, rows_from_json
from hds.utils import cli
from hds.utils.io import atomic_write_bytes, read_json

ROW_COLUMNS = (
    "seed",
    "sim_return",
    "real_return",
    "gap",
    "gap_relative",
    "solved_sim",
    "solved_real",
    "job",
)


def settings_of(rows: list[Row]) -> list[str]:
    """The swept keys that tell rows apart, besides the friction gap (part of the plant)."""
    return plots.varying_keys(rows, exclude=("friction_gap",))


def run_summaries(root: Path) -> list[tuple[Path, Summary]]:
    """Every run's summary below root, with its directory (a sweep's gathered summary is
    skipped: its jobs are read directly)."""
    found = []
    for path in sorted(root.rglob("summary.json")):
        data = read_json(path)
        if Summary.is_run(data):
            found.append((path.parent, Summary.from_json(data)))
    return found


def plant_of(summary: Summary, job_dir: Path) -> str:
    """The name of the plant a job's own rows were measured on: in its summary, or (written
    before plants had names) its config's."""
    name = summary.real.get("name")
    if name is None and (job_dir / "config.yaml").is_file():
        name = load_config(job_dir / "config.yaml").real.label()
    return name or "-"


def collect_rows(root: Path, found_loops: list[tuple] = ()) -> tuple[list[Row], list[tuple]]:
    """Every row of every run summary below root (a sweep's gathered summary is skipped: its
    jobs are read directly), each with its plant and friction gap, also the rows of the
    further plants a job evaluated its policies on (`eval_plants`) and of the rounds of
    `found_loops` (`loops`); and every (label: method and swept setting, (plant, friction
    gap), job, history of those runs), on each plant the runs were evaluated on. Both empty
    when root holds no run."""
    rows, runs = [], []
    for job_dir, summary in run_summaries(root):
        own = {
            "plant": plant_of(summary, job_dir),
            "friction_gap": summary.real.get("friction_gap"),
        }
        job = str(job_dir.relative_to(root)) if job_dir != root else "."
        job_rows = [  # a swept gap: its own
            replace(r, settings={**own, **r.settings}, job=job) for r in summary.rows
        ]
        eval_rows = [replace(r, job=job) for r in summary.rows_eval_plants]
        rows += job_rows + eval_rows
        runs.append((job, job_rows, summary.history))
        for column in dict.fromkeys(map(plant_column, eval_rows)):  # the same policies' curves
            runs.append((job, [r for r in eval_rows if plant_column(r) == column], summary.history))
    rows += loop_rows(found_loops, root)
    keys = settings_of(rows)
    histories = []
    for job, job_rows, history in runs:
        swept_gap = len({r.friction_gap for r in job_rows}) > 1
        for row, h in plots.histories_by_setting(
            job_rows, history, [*keys, "friction_gap"] if swept_gap else keys
        ):
            histories.append((plots.label(row, keys), plant_column(row), job, h))
    return rows, histories


def plant_truth(summary: Summary, job_dir: Path) -> list[dict] | None:
    """The effects a job's plant applied (friction scaled by its gap): in its summary, or
    (written before summaries recorded them) from its config; None when neither says."""
    if "effects" in summary.real:
        return summary.real["effects"]
    if (job_dir / "config.yaml").is_file():
        real = load_config(job_dir / "config.yaml").real
        return applied(real.effects, real.friction_gap)
    return None


def discoveries(root: Path, rows: list[Row], found_loops: list[tuple] = ()) -> list[dict]:
    """What gap discovery named below root, each beside the plant's truth: per run that trained
    on a corrected simulator (its rows' labels), and per round of each loop `found_loops`.
    Each: label, plant, friction_gap, job, effects (named, with ci95), truth, warnings."""
    rows = rows_from_json(rows)
    keys = settings_of(rows)
    labels = defaultdict(list)  # job -> its rows' labels (a job may sweep a setting inside)
    for r in rows:
        labels[(r.job, plant_column(r))].append(plots.label(r, keys))
    found = []
    for job_dir, summary in run_summaries(root):
        named = summary.discovery.get("effects")
        if named is None:
            continue
        job = str(job_dir.relative_to(root)) if job_dir != root else "."
        column = (plant_of(summary, job_dir), summary.real.get("friction_gap"))
        for label in dict.fromkeys(labels[(job, column)]):
            found.append(
                {
                    "label": label,
                    "plant": column[0],
                    "friction_gap": column[1],
                    "job": job,
                    "effects": named,
                    "truth": plant_truth(summary, job_dir),
                    "warnings": summary.discovery.get("warnings", []),
                }
            )
    from hds.simulators import method_name

    for loop_dir, cfg, rounds in found_loops:
        truth = applied(cfg.real.effects, cfg.real.friction_gap)
        for report in rounds:
            if not report.get("round"):  # round 0: the simulator as given, nothing named
                continue
            round_rows = rows_from_json(report["rows"])
            for label in dict.fromkeys(f"{method_name(cfg)}+{r.method}" for r in round_rows):
                found.append(
                    {
                        "label": label,
                        "plant": cfg.real.label(),
                        "friction_gap": cfg.real.friction_gap,
                        "job": str(loop_dir.relative_to(root)),
                        "effects": report["effects"],
                        "truth": truth,
                    }
                )
    return found


def told(root: Path, rows: list[Row], summary: list[dict], found_loops, figure: Path) -> str:
    """The story of the rows below root (hds.story: a few lines per method and plant), its
    figure (the plant reported at most gaps) written to `figure`."""
    columns = {plant_column(r) for r in rows}
    names = column_names(list(columns))
    text = story.story(summary, discoveries(root, rows, found_loops), names)
    shown = shown_column(columns)
    entries = [e for e in summary if plant_column(e) == shown]
    where = "/".join(root.resolve().parts[-2:])  # a sweep's name and time
    title = f"{where}: on the plant {names[shown]}, 95% intervals over seeds"
    plots.save(story.figure(entries, title), figure)
    return text


def sweep_story(sweep_dir: Path) -> tuple[str, Path]:
    """The story of a finished sweep (what `make run` ends with) and its figure,
    sweep_dir/plots/summary.png."""
    sweep_dir = Path(sweep_dir)
    found_loops = loops(sweep_dir)
    rows, _ = collect_rows(sweep_dir, found_loops)
    figure = sweep_dir / "plots" / "summary.png"
    return told(sweep_dir, rows, aggregate(rows), found_loops, figure), figure


def shown_column(columns: set) -> tuple:
    """The plant whose learning curves a report draws: the one reported at most friction gaps
    (the friction study's), at its nominal gap where it has one."""
    count = defaultdict(int)
    for plant, _ in columns:
        count[plant] += 1
    plant = max(sorted(count), key=count.get)
    gaps = sorted((g for p, g in columns if p == plant), key=lambda g: (g is None, g))
    return plant, 1.0 if 1.0 in gaps else gaps[-1]


def loops(root: Path) -> list[tuple]:
    """(directory, config, round reports) of every sim2real loop below root
    (`python -m hds.loop`'s loop.json)."""
    return [
        (path.parent, load_config(path.parent / "config.yaml"), read_json(path)["rounds"])
        for path in sorted(root.rglob("loop.json"))
    ]


def loop_rows(found: list[tuple], root: Path) -> list[Row]:
    """The rows of every round of the `loops` found below root, each with its loop's plant,
    labelled by the loop's method and round (pods_cl+loop1, hds+mlp+loop1): loops of two
    methods on one plant stay apart."""
    from hds.simulators import method_name

    rows = []
    for loop_dir, cfg, rounds in found:
        own = {"plant": cfg.real.label(), "friction_gap": cfg.real.friction_gap}
        job, method = str(loop_dir.relative_to(root)), method_name(cfg)
        for report in rounds:
            rows += [
                replace(r, settings={**own, **r.settings}, job=job, method=f"{method}+{r.method}")
                for r in rows_from_json(report["rows"])
            ]
    return rows


def plant_column(row: Row | dict) -> tuple:
    """A row's (or a report entry's) plant at its friction gap: the column it is reported in."""
    return row["plant"], row.get("friction_gap")


def column_names(columns: list[tuple]) -> dict:
    """A heading per (plant, friction gap): the plant's name, with the gap where a plant is
    reported at several."""
    gaps = defaultdict(set)
    for plant, gap in columns:
        gaps[plant].add(gap)
    return {(p, g): f"{p} x{g:g}" if len(gaps[p]) > 1 else p for p, g in columns}


def aggregate(rows: list[Row] | list[dict]) -> list[dict]:
    """Mean and 95% interval over seeds of each method on each plant (at its friction gap) and
    swept setting (`label`: the method and its settings); `rows`: Rows, or as JSON."""
    rows = rows_from_json(rows)
    keys = settings_of(rows)
    groups = defaultdict(list)
    for r in rows:
        groups[(plots.label(r, keys), plant_column(r))].append(r)
    out = []
    order = lambda kv: (kv[0][0], kv[0][1][0], kv[0][1][1] or 0)  # noqa: E731
    for (name, (plant, gap)), group in sorted(groups.items(), key=order):
        first = group[0]
        entry = {"method": first.method, "label": name, "plant": plant, "friction_gap": gap}
        entry["runs"] = len(group)
        entry |= {k: first.settings[k] for k in keys if k in first.settings}
        for key in ("sim_return", "real_return", "gap"):
            entry[key] = mean_ci([getattr(r, key) for r in group])
        for key in ("solved_sim", "solved_real"):
            if all(getattr(r, key) is not None for r in group):
                entry[key] = sum(bool(getattr(r, key)) for r in group)
        out.append(entry)
    return out


def number(x: float) -> str:
    """Three significant digits, without an exponent for the returns of these tasks."""
    return f"{x:.3g}" if abs(x) < 1000 else f"{x:.0f}"


def markdown_table(summary: list[dict]) -> str:
    solved = all("solved_sim" in e for e in summary)
    names = column_names([plant_column(e) for e in summary])
    lines = [
        "| method | plant | runs | sim return | real return | sim2real gap |"
        + (" solved (sim, real) |" if solved else ""),
        "| --- | --- | ---: | ---: | ---: | ---: |" + (" ---: |" if solved else ""),
    ]
    fmt = lambda m, lo, hi: f"{number(m)} [{number(lo)}, {number(hi)}]"  # noqa: E731
    for e in summary:
        lines.append(
            f"| {e['label']} | {names[plant_column(e)]} | {e['runs']} | {fmt(*e['sim_return'])} "
            f"| {fmt(*e['real_return'])} | {fmt(*e['gap'])} |"
            + (f" {e['solved_sim']}, {e['solved_real']} |" if solved else "")
        )
    return "\n".join(lines)


def pivot_table(summary: list[dict], key: str) -> str:
    """One row per method (and setting), one column per plant: the mean over seeds."""
    means = {(e["label"], plant_column(e)): e[key][0] for e in summary}
    return _pivot(summary, lambda label, column: number(means[(label, column)]))


def relative_cost_table(summary: list[dict], reference: str = "oracle") -> str | None:
    """Per method and plant, its real cost (minus the return) over the `reference` method's
    on that plant: 1 is as good as the oracle, above 1 worse. None without it."""
    cost = {(e["label"], plant_column(e)): -e["real_return"][0] for e in summary}
    if not any(label == reference for label, _ in cost):
        return None

    def cell(label, column):
        ref = cost.get((reference, column))
        return f"{cost[(label, column)] / ref:.2f}" if ref else "-"

    return _pivot(summary, cell)


def _pivot(summary: list[dict], cell) -> str:
    columns = sorted({plant_column(e) for e in summary}, key=lambda c: (c[0], c[1] or 0))
    names = column_names(columns)
    labels = list(dict.fromkeys(e["label"] for e in summary))
    present = {(e["label"], plant_column(e)) for e in summary}
    lines = [
        "| method | " + " | ".join(names[c] for c in columns) + " |",
        "| --- |" + " ---: |" * len(columns),
    ]
    for m in labels:
        cells = [cell(m, c) if (m, c) in present else "-" for c in columns]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_csv(rows: list[Row], path: Path) -> None:
    """One row per run: method, plant, friction gap, every swept setting, seed, returns, gap,
    job."""
    rows = rows_from_json(rows)
    columns = ["method", "plant", "friction_gap", *settings_of(rows), *ROW_COLUMNS]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(r.to_json() for r in rows)
    atomic_write_bytes(path, buf.getvalue().encode())


def discovery_sections(root: Path, out: Path) -> list[str]:
    """A section per gap-discovery report below root; its figures are linked in place, or
    copied into out/plots/ when the report is written elsewhere (out != root)."""
    sections = []
    numbered = lambda p: [(0, int(x), "") if x.isdigit() else (1, 0, x) for x in p.parts]  # noqa: E731
    for path in sorted(root.rglob("report.json"), key=numbered):
        report = read_json(path)
        found = report.get("missing_effects", [])
        values = lambda e: ", ".join(f"{k} {v:.4g}" for k, v in e["params"].items())  # noqa: E731
        names = ", ".join(f"{e['name']}@{e['target']} ({values(e)})" for e in found) or "none"
        warnings = "".join(f"\n\n> warning: {w}" for w in report.get("warnings", []))
        rel = path.parent.relative_to(root)
        images = []
        for png in sorted((path.parent / "plots").glob("*.png")):
            if out == root:
                link = rel / "plots" / png.name
            else:
                link = Path("plots") / "_".join(("discovery", *rel.parts, png.name))
                atomic_write_bytes(out / link, png.read_bytes())
            images.append(f"![{png.stem}]({link})")
        full = Path(os.path.relpath(path.parent / "report.md", out))
        sections.append(
            f"### Gap discovery: {rel if rel.parts else root.name}\n\n"
            f"Missing effects named: {names}. "
            f"Full report: [{full}]({full}){warnings}\n\n"
            + discovery_errors(report)
            + "\n".join(images)
        )
    return sections


def unused_models(root: Path) -> list[str]:
    """A line per run below root whose learned model was fitted but not used (dynamics.
    require_better): HDS there trained without it."""
    lines = []
    for path in sorted(root.rglob("summary.json")):  # the learned model's report, as it is
        model = read_json(path).get("dynamics", {})
        if "not_used_because" in model:
            job = path.parent.relative_to(root) if path.parent != root else Path(".")
            lines.append(f"- `{job}`: {model['not_used_because']}")
    if not lines:
        return []
    return [
        "Learned models not used (predicting the held-out plant episodes no better than the "
        "simulator; HDS trained without them, `dynamics.require_better`):",
        "",
        *lines,
        "",
    ]


def loop_sections(found: list[tuple], root: Path, out: Path) -> list[str]:
    """A section per loop `found` below root: each round's named effects, real return and
    gap, and its figure (copied into out/plots/ when the report is written elsewhere)."""
    from hds.loop import round_row

    sections = []
    for loop_dir, cfg, rounds in found:
        rel = loop_dir.relative_to(root)
        lines = [
            f"### Sim2real loop: {rel} ({cfg.real.label()})",
            "",
            "| round | named (95% interval) | real return [95%] | sim2real gap | episodes |",
            "| ---: | --- | ---: | ---: | ---: |",
        ]
        for report in rounds:
            r = round_row(report)
            lines.append(
                f"| {r['round']} | {r['named']} | {number(r['real_return'])} {r['interval']} "
                f"| {number(r['gap'])} | {r['episodes']} |"
            )
        lines += [
            f"\nRound {report['round']}: the learned model was not used, predicting no better "
            f"than the round's simulator ({report['model_not_used_because']})."
            for report in rounds
            if "model_not_used_because" in report
        ]
        figure = loop_dir / "plots" / "loop_rounds.png"
        if figure.is_file():
            link = rel / "plots" / figure.name
            if out != root:
                link = Path("plots") / "_".join(("loop", *rel.parts, figure.name))
                atomic_write_bytes(out / link, figure.read_bytes())
            lines += ["", f"![loop_rounds]({link})"]
        sections.append("\n".join(lines) + "\n")
    return sections


def optuna_sections(root: Path) -> list[str]:
    """A section per Optuna study below root (hydra/sweeper=optuna writes
    optimization_results.yaml into its sweep directory): the best trial, and each trial's
    sampled settings and objective (what its job returned: the mean over its seeds of
    `objective`) beside the other return, best first; failed trials counted."""
    sections = []
    for path in sorted(root.rglob("optimization_results.yaml")):
        study = OmegaConf.load(path)
        keys = list(study.best_params)
        trials = [t for job in sorted(path.parent.iterdir()) if (t := optuna_trial(job, keys))]
        if not trials:
            continue
        objective = trials[0]["objective"]
        other = "sim_return" if objective == "real_return" else "real_return"
        trials.sort(key=lambda t: -t[objective].mean if np.isfinite(t[objective].mean) else np.inf)
        failed = sorted(p.parent.name for p in path.parent.glob("*/failed.txt"))
        best = ", ".join(f"{k}={v:.4g}" for k, v in study.best_params.items())
        rel = path.parent.relative_to(root) if path.parent != root else Path(root.name)
        fmt = lambda c: f"{number(c.mean)} [{number(c.low)}, {number(c.high)}]"  # noqa: E731
        lines = [
            f"### Optuna study: {rel}",
            "",
            f"Best: {best}, mean {objective} {number(float(study.best_value))}. Its "
            f"{len(trials)} finished trials, best first (the tables above pool every trial's "
            "runs)" + (f"; failed: {', '.join(failed)} (their failed.txt)" if failed else "") + ":",
            "",
            "| trial | " + " | ".join(keys) + f" | {objective} [95%] | {other} [95%] |",
            "| ---: |" + " ---: |" * (len(keys) + 2),
        ]
        for t in trials:
            cells = [f"{t['params'][k]:.4g}" if k in t["params"] else "-" for k in keys]
            values = f" | {fmt(t[objective])} | {fmt(t[other])} |"
            lines.append(f"| {t['job']} | " + " | ".join(cells) + values)
        sections.append("\n".join(lines) + "\n")
    return sections


def optuna_trial(job: Path, keys: list[str]) -> dict | None:
    """One finished trial of an Optuna study: its sampled `keys` (its Hydra overrides), its
    objective's name, and the real and simulator returns of its own method's runs (mean and
    95% interval over seeds); None if unfinished."""
    from hds.simulators import method_name

    overrides = job / ".hydra" / "overrides.yaml"
    if not all(p.is_file() for p in (overrides, job / "summary.json", job / "config.yaml")):
        return None
    cfg = load_config(job / "config.yaml")
    own = [r for r in Summary.read(job / "summary.json").rows if r.method == method_name(cfg)]
    given = dict(o.split("=", 1) for o in OmegaConf.load(overrides))
    return {
        "job": job.name,
        "params": {k: float(given[k]) for k in keys if k in given},
        "objective": cfg.objective,
        **{key: mean_ci([getattr(r, key) for r in own]) for key in ("real_return", "sim_return")},
    }


def discovery_errors(report: dict) -> str:
    """k-step (rollout) RMSE per state variable before and after the named effects were added,
    on each data set of the discovery (identification, held-out, validation)."""
    sets = report.get("errors") or {}
    if not sets:
        return ""
    names = next(iter(sets.values()))["before"]["names"]
    lines = [
        f"k-step prediction error (RMSE, {report.get('horizon_steps', 'k')} steps), before -> "
        "after the correction:",
        "",
        "| data | " + " | ".join(names) + " | normalized |",
        "| --- |" + " ---: |" * (len(names) + 1),
    ]
    for name, err in sets.items():
        before, after = err["before"], err["after"]
        cells = [
            f"{b:.3g} -> {a:.3g}" for b, a in zip(before["rollout_rmse"], after["rollout_rmse"])
        ]
        norm = f"{before['rollout_nrmse']:.3g} -> {after['rollout_nrmse']:.3g}"
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {norm} |")
    return "\n".join(lines) + "\n\n"


def build(root: str | Path, out: str | Path | None = None) -> Path:
    """Write the report of the run or sweep at root into out (default: root itself)."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root} is not a directory; give a run or sweep directory")
    if out is None:  # a discovery directory has a report.md of its own: leave it be
        out = root / "report" if (root / "report.json").is_file() else root
    out = Path(out)
    found_loops = loops(root)
    rows, histories = collect_rows(root, found_loops)
    if not rows:
        sections = discovery_sections(root, out)
        if not sections:
            raise FileNotFoundError(
                f"nothing to report below {root}: hds.report expects a run or sweep directory "
                "(summary.json, written by `python -m hds.run`) or a gap-discovery directory "
                "(report.json, written by `python -m hds.discover`)"
            )
        text = [f"# Report: {root.name}", "", "No training run here: gap discovery only.", ""]
        text += sections
        return atomic_write_bytes(out / "report.md", ("\n".join(text) + "\n").encode())
    summary = aggregate(rows)
    columns = {plant_column(r) for r in rows}
    shown = shown_column(columns)
    swept = [c for c in columns if c[0] == shown[0]]  # the plant reported at several gaps
    shown_histories = [(m, j, h) for m, c, j, h in histories if c == shown]
    repeated = len({m for m, *_ in shown_histories}) < len(shown_histories)
    figures = {}
    if shown_histories:  # none where only loops are below root
        figures["report_learning_curves"] = plots.learning_curves(
            {f"{m} ({j})" if repeated else m: h for m, j, h in shown_histories}
        )
    figures["report_sim_vs_real"] = plots.sim_vs_real([r for r in rows if plant_column(r) == shown])
    if len(swept) > 1:
        figures["report_gap_vs_friction"] = plots.gap_vs_friction(
            [{**e, "method": e["label"]} for e in summary if e["plant"] == shown[0]]
        )
    for name, fig in figures.items():
        plots.save(fig, out / "plots" / f"{name}.png")
    told_text = told(root, rows, summary, found_loops, out / "plots" / "report_summary.png")
    write_csv(rows, out / "report.csv")
    text = [
        f"# Report: {root.name}",
        "",
        "## Summary",
        "",
        "Per plant, each method (best on the plant first): mean and 95% interval over seeds.",
        "",
        "```text",
        told_text,
        "```",
        "",
        "![report_summary](plots/report_summary.png)",
        "",
        "## Every method, plant and setting",
        "",
        "Mean and 95% interval over seeds. gap = return on the simulator - on the real plant.",
        "",
        markdown_table(summary),
        "",
        *(
            [
                "Mean real-plant return over seeds, per plant (x: its friction's scale, "
                "real.friction_gap):",
                "",
                pivot_table(summary, "real_return"),
                "",
                "Mean sim2real gap:",
                "",
                pivot_table(summary, "gap"),
                "",
                *(
                    [
                        "Real cost (minus the mean real return) over the oracle's at the same "
                        "plant (1: as good as the oracle; above: worse):",
                        "",
                        relative,
                        "",
                    ]
                    if (relative := relative_cost_table(summary))
                    else []
                ),
            ]
            if len(columns) > 1
            else []
        ),
        "One row per seed: [report.csv](report.csv).",
        "",
    ]
    if len(columns) > 1:
        text += [f"Learning curves and sim-vs-real bars: {column_names(list(columns))[shown]}.", ""]
    text += [f"![{name}](plots/{name}.png)" for name in figures]
    text += (
        [""]
        + unused_models(root)
        + optuna_sections(root)
        + loop_sections(found_loops, root, out)
        + discovery_sections(root, out)
    )
    path = atomic_write_bytes(out / "report.md", ("\n".join(text) + "\n").encode())
    return path


def animated_plant(cfg, run_dir: Path, eval_plant: str | None):
    """The plant config `animate_run` deploys on: the run's own, or its eval_plants entry."""
    if eval_plant is None:
        return cfg.real
    if eval_plant not in cfg.eval_plants:
        raise ValueError(
            f"gif_plant={eval_plant}: {run_dir} has no such eval_plants entry; choose one of "
            f"{sorted(cfg.eval_plants)}, or leave gif_plant out for the run's own plant"
        )
    return cfg.eval_plants[eval_plant]


def run_to_animate(directory: Path, job: str) -> Path:
    """The run directory `gif=JOB` names: the run itself, or a sweep's job JOB (`gif=true`,
    job "": its first job)."""
    if job:
        return directory / job
    if (directory / "config.yaml").is_file():
        return directory
    runs = sorted((p.parent for p in directory.glob("*/config.yaml")), key=lambda p: p.name)
    if not runs:
        raise FileNotFoundError(f"no run directory (with config.yaml) in {directory} to animate")
    return runs[0]


def animate_run(
    run_dir: Path,
    method: str | None = None,
    seed_index: int = 0,
    out_dir: Path | None = None,
    eval_plant: str | None = None,
) -> Path:
    """One episode of a finished run's policy (`method`, default the run's own; the
    seed_index-th run of its batch) on the simulator it trained on beside the run's plant (or
    its eval_plants entry `eval_plant`), animated into out_dir (default: the run's plots/), its
    trajectories plotted beside."""
    from hds.policy import evaluate_policy, load_policy, run_config

    run_dir = Path(run_dir)
    cfg = run_config(run_dir)
    real_cfg = animated_plant(cfg, run_dir, eval_plant)
    policy = load_policy(run_dir, method, **cfg.runs()[seed_index])
    sim = evaluate_policy(policy, episodes=1, plant=policy.training_plant())
    real = evaluate_policy(policy, real_cfg, episodes=1)
    out = Path(out_dir or run_dir / "plots") / f"{policy.method}_sim_vs_real.gif"
    figure = plots.trajectories(
        sim.episodes.obs[0], real.episodes.obs[0], policy.obs_names, policy.dt
    )
    plots.save(figure, out.with_name(f"{policy.method}_trajectories.png"))
    return animate_episodes(
        sim.episodes,
        real.episodes,
        policy.obs_names,
        real_cfg.plant,
        policy.dt,
        out,
        policy.env.xml,
    )


KEYS = {"dir": Path, "out": Path, "gif": str, "gif_plant": str}


def main(argv: list[str]) -> None:
    args, _ = cli.parse(argv, KEYS, "hds.report", required=("dir",))
    directory, out_dir = args["dir"], args.get("out")
    gif = {"true": "", "false": None}.get(args.get("gif", "false").lower(), args.get("gif"))
    gif_plant = args.get("gif_plant")
    if gif_plant is not None and gif is None:
        raise ValueError("gif_plant chooses the plant of gif's animation: add gif=true (or JOB)")
    animated = None
    if gif is not None:  # a bad JOB or plant is refused before the report is written
        animated = run_to_animate(directory, gif)
        from hds.policy import run_config

        animated_plant(run_config(animated), animated, gif_plant)
    print(f"wrote {build(directory, out_dir)}")
    if animated is not None:
        out = out_dir / "plots" if out_dir else None
        print(f"wrote {animate_run(animated, out_dir=out, eval_plant=gif_plant)}")


if __name__ == "__main__":
    cli.run(main)
