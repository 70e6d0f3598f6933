"""Figures a person would rather look at than read. Headless (Agg); each returns a Figure."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def learning_curves(histories: dict[str, dict]) -> plt.Figure:
    """histories: {method: {metric: [n_seeds, n_epochs]}}; mean and range over seeds."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for method, h in histories.items():
        for ax, key in zip(axes, ("return", "loss", "step_size")):
            values = np.asarray(h[key], dtype=float)
            epochs = np.arange(values.shape[1])
            (line,) = ax.plot(epochs, values.mean(0), label=method)
            if values.shape[0] > 1:
                ax.fill_between(
                    epochs, values.min(0), values.max(0), alpha=0.2, color=line.get_color()
                )
            ax.set_xlabel("epoch")
            ax.set_title(
                {
                    "return": "return on the simulator",
                    "loss": "regression loss",
                    "step_size": "action step size",
                }[key]
            )
    axes[1].set_yscale("log")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 6), frameon=False)
    fig.tight_layout(rect=(0, 0.08 * (1 + (len(labels) - 1) // 6), 1, 1))
    return fig


def sim_vs_real(rows: list[dict]) -> plt.Figure:
    """Mean return on the simulator and on the real plant per method, seeds as dots."""
    methods = list(dict.fromkeys(r["method"] for r in rows))
    fig, ax = plt.subplots(figsize=(1.8 + 1.6 * len(methods), 3.6))
    x = np.arange(len(methods))
    for offset, key, label in (
        (-0.18, "sim_return", "simulator"),
        (0.18, "real_return", "real plant"),
    ):
        vals = [[r[key] for r in rows if r["method"] == m] for m in methods]
        ax.bar(x + offset, [np.mean(v) for v in vals], width=0.34, label=label, alpha=0.8)
        for i, v in enumerate(vals):
            ax.scatter(np.full(len(v), x[i] + offset), v, color="k", s=8, zorder=3)
    ax.set_xticks(x, methods)
    ax.set_ylabel("return")
    ax.set_title("sim2real gap")
    ax.legend()
    fig.tight_layout()
    return fig


def gap_vs_friction(summary: list[dict]) -> plt.Figure:
    """Real-plant return and sim2real gap against the friction gap, per method, with the 95%
    interval over seeds (entries of hds.report.aggregate)."""
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
    axes[0].legend()
    fig.tight_layout()
    return fig


def save(fig: plt.Figure, path: Path) -> Path:
    """Write fig atomically and close it (pyplot keeps every open figure alive)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(path)
    return path
