"""Figures a person would rather look at than read. Headless (Agg); each returns a Figure."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hds.config import SWEEP_KEYS
from hds.utils.runtime import pyplot

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def varying_keys(rows: list[dict], exclude=()) -> list[str]:
    """The swept keys whose values differ between rows: what tells their runs apart."""
    return [k for k in SWEEP_KEYS if k not in exclude and len({r.get(k) for r in rows}) > 1]


def label(row: dict, keys: list[str]) -> str:
    """A row's method and its swept settings among `keys`: `pods step_size=0.04`."""
    return " ".join([str(row["method"]), *(f"{k}={row[k]:g}" for k in keys if k in row)])


def histories_by_setting(rows: list[dict], histories: dict, keys: list[str]) -> list[tuple]:
    """One run's {method: {metric: [n_runs][epochs]}} split by the settings among `keys`:
    [(first row of the group, its history)]. A method's history rows follow its rows."""
    out = []
    for method, history in histories.items():
        method_rows = [r for r in rows if r["method"] == method]
        groups: dict[str, list[int]] = {}
        for i, r in enumerate(method_rows):
            groups.setdefault(label(r, keys), []).append(i)
        for index in groups.values():
            picked = {k: [v[i] for i in index] for k, v in history.items()}
            out.append((method_rows[index[0]], picked))
    return out


def learning_curves(histories: dict[str, dict]) -> Figure:
    """histories: {method: {metric: [n_seeds, n_epochs]}}; mean and range over seeds. The
    return axis is symlog: the first epochs' returns (thousands) and the last (a few units,
    where methods differ) both read."""
    from matplotlib.patches import Patch

    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    banded = 0
    for method, h in histories.items():
        for ax, key in zip(axes, ("return", "loss", "step_size")):
            values = np.asarray(h[key], dtype=float)
            epochs = np.arange(values.shape[1])
            (line,) = ax.plot(epochs, values.mean(0), label=method)
            if values.shape[0] > 1:
                banded = max(banded, values.shape[0])
                ax.fill_between(
                    epochs, values.min(0), values.max(0), alpha=0.2, color=line.get_color()
                )
            ax.set_xlabel("epoch")
            title, ylabel = {
                "return": ("return on the simulator", "return (sum of rewards)"),
                "loss": ("regression loss", "mean squared error"),
                "step_size": ("action step size", "alpha"),
            }[key]
            ax.set_title(title)
            ax.set_ylabel(ylabel)
    axes[0].set_yscale("symlog", linthresh=1.0)  # linear within [-1, 1], log beyond
    axes[0].set_ylabel("return (symlog)")
    axes[1].set_yscale("log")
    handles, labels = axes[0].get_legend_handles_labels()
    if banded:  # what the shading is
        handles.append(Patch(color="0.6", alpha=0.4))
        labels.append(f"line: mean over seeds; band: min to max ({banded} seeds)")
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6), frameon=False)
    fig.tight_layout(rect=(0, 0.08 * (1 + (len(labels) - 1) // 6), 1, 1))
    return fig


def sim_vs_real(rows: list[dict]) -> Figure:
    """Mean return on the simulator and on the real plant per method and swept setting, seeds
    as dots."""
    keys = varying_keys(rows)
    rows = [{**r, "method": label(r, keys)} for r in rows]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(3.2 + 1.6 * len(methods), 3.6))
    x = np.arange(len(methods))
    for offset, key, where in (
        (-0.18, "sim_return", "simulator"),
        (0.18, "real_return", "real plant"),
    ):
        vals = [[r[key] for r in rows if r["method"] == m] for m in methods]
        ax.bar(x + offset, [np.mean(v) for v in vals], width=0.34, label=where, alpha=0.8)
        for i, v in enumerate(vals):
            ax.scatter(np.full(len(v), x[i] + offset), v, color="k", s=8, zorder=3)
    ax.set_xticks(
        x,
        methods,
        rotation=20 if len(methods) > 3 else 0,
        ha="right" if len(methods) > 3 else "center",
    )
    ax.set_ylabel("return")
    ax.set_title("sim2real gap")
    ax.legend(
        loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False
    )  # beside, not on, the bars
    fig.tight_layout()
    return fig


def gap_vs_friction(summary: list[dict]) -> Figure:
    """Real-plant return and sim2real gap against the friction gap, per method, with the 95%
    interval over seeds (entries of hds.report.aggregate)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for method in dict.fromkeys(e["method"] for e in summary):
        entries = sorted(
            (e for e in summary if e["method"] == method), key=lambda e: e["friction_gap"]
        )
        x = [e["friction_gap"] for e in entries]
        for ax, key in zip(axes, ("real_return", "gap")):
            mean, lo, hi = (np.array([e[key][i] for e in entries]) for i in range(3))
            (line,) = ax.plot(x, mean, "o-", label=method)
            ax.fill_between(x, lo, hi, alpha=0.2, color=line.get_color())
    axes[0].set_title("return on the real plant")
    axes[1].set_title("sim2real gap (sim - real)")
    for ax in axes:
        ax.set_xlabel("friction gap (x the plant's friction)")
        # linear near 0, logarithmic beyond: policies that work (returns of a few units) and
        # those that fail (thousands) in one figure
        ax.set_yscale("symlog", linthresh=10)
    handles, labels = axes[0].get_legend_handles_labels()  # below the axes, over no line
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6), frameon=False)
    fig.tight_layout(rect=(0, 0.08 * (1 + (len(labels) - 1) // 6), 1, 1))
    return fig


def loop_rounds(rounds: list[dict]) -> Figure:
    """The sim2real loop's real-plant return and sim2real gap per round, with the 95% interval
    over the runs (reports of hds.loop.run_loop)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    x = [r["round"] for r in rounds]
    for ax, key, title in (
        (axes[0], "real_return", "return on the real plant"),
        (axes[1], "gap", "sim2real gap (sim - real)"),
    ):
        mean, lo, hi = (np.array([r[key][i] for r in rounds]) for i in range(3))
        ax.errorbar(x, mean, yerr=[mean - lo, hi - mean], fmt="o-", capsize=4)
        ax.set_xticks(x)
        ax.set_xlabel("loop round (0: the simulator as given)")
        ax.set_ylabel("return" if key == "real_return" else "gap")
        ax.set_title(title)
    fig.tight_layout()
    return fig


def trajectories(sim_obs, real_obs, names, dt: float) -> Figure:
    """One episode of a policy from the same initial state on the simulator and on the plant:
    each observed variable against time."""
    n = len(names)
    cols = min(n, 4)
    rows = -(-n // cols)
    plt = pyplot()
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    t = np.arange(len(sim_obs)) * dt
    for i, ax in enumerate(axes.flat):
        if i >= n:
            ax.axis("off")
            continue
        ax.plot(t, sim_obs[:, i], label="simulator")
        ax.plot(t, real_obs[:, i], "--", label="plant")
        ax.set_title(names[i])
        ax.set_xlabel("time (s)")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=2, frameon=False)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    return fig


def save(fig: Figure, path: Path) -> Path:
    """Write fig atomically and close it (pyplot keeps every open figure alive)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt = pyplot()
    plt.close(fig)
    tmp.replace(path)
    return path
