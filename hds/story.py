"""What a sweep found, in a few lines per method and one figure for a slide.

The end of `make run` (a multirun's last words, hds.callbacks.SweepSummary) and the top of
every `python -m hds.report`: per plant, each method, best on the plant first, with its mean
real return and the sim2real gap (95% intervals over seeds), how many seeds solve the task on
the simulator and on the plant, its real cost over the oracle's, and, where gap discovery ran,
the effects it named with their intervals beside what the plant really applies. Built from
hds.report's aggregate entries (one per method, plant and swept setting) and its discoveries.
"""

from __future__ import annotations

import numpy as np

from hds.utils.runtime import pyplot

ORACLE = "oracle"


def column_of(entry: dict) -> tuple:
    """The plant (and friction gap) an aggregate entry or discovery was measured on."""
    return entry["plant"], entry.get("friction_gap")


def _number(x: float) -> str:
    return f"{x:.3g}" if abs(x) < 1000 else f"{x:.0f}"


def interval(value) -> str:
    """A (mean, low, high) as `-4.76 [-6.13, -3.40]`."""
    mean, lo, hi = value
    return f"{_number(mean)} [{_number(lo)}, {_number(hi)}]"


def ranked(entries: list[dict]) -> list[dict]:
    """Best mean real return first (a run with no finite return last)."""
    key = lambda e: e["real_return"][0] if np.isfinite(e["real_return"][0]) else -np.inf  # noqa: E731
    return sorted(entries, key=key, reverse=True)


def named_beside_truth(named: list[dict], truth: list[dict] | None) -> str:
    """The effects discovery named, each parameter with its 95% interval and the plant's own
    value beside it; the plant's effects it did not name, as missed. `truth`: the effects the
    plant applies (None: not recorded)."""
    truth_of = {(t["name"], t["target"]): t["params"] for t in truth or []}
    parts = []
    for e in named:
        own = truth_of.get((e["name"], e["target"]))
        values = []
        for p, v in e["params"].items():
            text = f"{p} {_number(v)}"
            if p in e.get("ci95", {}):
                lo, hi = e["ci95"][p]
                text += f" [{_number(lo)}, {_number(hi)}]"
            if own is not None and p in own:
                text += f" (plant: {_number(own[p])})"
            values.append(text)
        where = "" if own is not None or truth is None else " (not in the plant)"
        parts.append(f"{e['name']}@{e['target']} {', '.join(values)}{where}")
    text = "; ".join(parts) or "nothing"
    if truth is not None:
        named_keys = {(e["name"], e["target"]) for e in named}
        missed = [t for t in truth if (t["name"], t["target"]) not in named_keys]
        if missed:
            text += "; missed: " + "; ".join(
                f"{t['name']}@{t['target']} "
                + ", ".join(f"{p} {_number(v)}" for p, v in t["params"].items())
                for t in missed
            )
        elif not truth and not named:
            text += " (the plant has no effect either)"
    elif named:
        text += " (the plant's own values were not recorded)"
    return text


def method_lines(entry: dict, oracle_cost: float | None, found: list[dict]) -> list[str]:
    """One method on one plant: its returns, solved seeds and cost, and its discoveries."""
    runs = entry["runs"]
    lines = [
        f"{entry['label']} ({runs} seed{'s' if runs != 1 else ''})",
        f"  real return {interval(entry['real_return'])}   sim2real gap {interval(entry['gap'])}",
    ]
    facts = []
    if "solved_sim" in entry:
        facts.append(
            f"solved by {entry['solved_sim']}/{runs} on the simulator, "
            f"{entry['solved_real']}/{runs} on the plant"
        )
    cost = -entry["real_return"][0]
    if oracle_cost and entry["method"] != ORACLE and np.isfinite(cost):
        facts.append(f"cost {cost / oracle_cost:.2f}x the oracle's")
    if facts:
        lines.append("  " + "; ".join(facts))
    for d in found:
        lines.append("  discovery named " + named_beside_truth(d["effects"], d.get("truth")))
        lines += [f"  discovery warned: {w}" for w in d.get("warnings", [])]
    return lines


def story(summary: list[dict], discoveries: list[dict] = (), names: dict | None = None) -> str:
    """The few lines per method of every plant in `summary` (hds.report.aggregate's entries;
    `discoveries`: {label, plant, friction_gap, effects, truth, warnings} each; `names`: a
    heading per plant column, default the plant's name)."""
    blocks = []
    columns = list(dict.fromkeys(column_of(e) for e in summary))
    for column in sorted(columns, key=lambda c: (c[0], c[1] or 0)):
        entries = ranked([e for e in summary if column_of(e) == column])
        oracle = [e for e in entries if e["label"] == ORACLE]
        oracle_cost = -oracle[0]["real_return"][0] if oracle else None
        if oracle_cost is not None and not (np.isfinite(oracle_cost) and oracle_cost > 0):
            oracle_cost = None  # a ratio to a cost of 0 (or a diverged oracle) says nothing
        heading = (names or {}).get(column) or column[0]
        best = entries[0]
        lines = [
            f"On the plant {heading}: best {best['label']}, real return "
            f"{interval(best['real_return'])}"
        ]
        for entry in entries:
            found = [
                d for d in discoveries if d["label"] == entry["label"] and column_of(d) == column
            ]
            lines += method_lines(entry, oracle_cost, found)
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


def figure(summary: list[dict], title: str = ""):
    """The real return per method with its 95% interval, and the sim2real gap, on one plant
    (`summary`: its aggregate entries), best first: two panels of horizontal bars, each row
    labelled with its mean and interval (readable where the methods differ by little)."""
    entries = ranked(summary)[::-1]  # barh draws upwards: the best on top
    y = np.arange(len(entries))
    fig, axes = pyplot().subplots(1, 2, figsize=(11, 1.4 + 0.6 * len(entries)))
    for ax, key, heading in (
        (axes[0], "real_return", "return on the plant (higher is better)"),
        (axes[1], "gap", "sim2real gap: simulator - plant"),
    ):
        mean, lo, hi = (np.array([e[key][i] for e in entries], dtype=float) for i in range(3))
        ax.barh(y, mean, xerr=[mean - lo, hi - mean], height=0.6, capsize=4, alpha=0.8)
        ax.axvline(0.0, color="k", lw=0.6)
        size = np.abs(mean[np.isfinite(mean) & (mean != 0)])
        if size.size and size.max() > 50 * np.median(size):  # a failed method beside working
            ax.set_xscale("symlog", linthresh=float(np.median(size)))
        ax.set_title(heading, fontsize=10)
    axes[0].set_yticks(y, [f"{e['label']}\n{interval(e['real_return'])}" for e in entries])
    axes[1].set_yticks(y, [interval(e["gap"]) for e in entries])
    axes[1].yaxis.tick_right()  # the gap's numbers beside its bars, the methods on the left
    fig.suptitle(title or "real return and sim2real gap, 95% intervals over seeds", fontsize=11)
    fig.tight_layout()
    return fig
