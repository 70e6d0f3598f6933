"""Figures of the discovery report (headless, Agg): each function returns a Figure."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from hds.discover.compare import Errors, Residuals  # noqa: E402
from hds.discover.locate import Location  # noqa: E402
from hds.effects.library import effect_type  # noqa: E402


def errors(before: Errors, after: Errors, names, scale, title: str) -> plt.Figure:
    """One-step and k-step RMSE per variable, before and after, in units of each signal's std."""
    scale = np.asarray(scale, dtype=float)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
    x = np.arange(len(names))
    for ax, key, label in (
        (axes[0], "one_step_rmse", "one-step"),
        (axes[1], "rollout_rmse", "k-step rollout"),
    ):
        for offset, err, tag in ((-0.2, before, "before"), (0.2, after, "after")):
            ax.bar(x + offset, getattr(err, key) / scale, width=0.38, label=tag)
        ax.set_xticks(x, names, rotation=20)
        ax.set_ylabel("RMSE / signal std")
        ax.set_title(f"{label} error, {title}")
    axes[0].legend()
    fig.tight_layout()
    return fig


def locate(loc: Location, bins: int) -> plt.Figure:
    """Left: eta^2 of every (variable, feature) pair; right: the most telling one."""
    feats = list(loc.features)
    eta = np.zeros((len(loc.variables), len(feats)))
    for row in loc.table:
        eta[loc.variables.index(row["variable"]), feats.index(row["feature"])] = row["eta2"]
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2), gridspec_kw={"width_ratios": [1.2, 1]})
    im = axes[0].imshow(eta, vmin=0, vmax=1, cmap="viridis", aspect="auto")
    axes[0].set_yticks(
        range(len(loc.variables)), [f"{v} ({s:.0%})" for v, s in zip(loc.variables, loc.share)]
    )
    axes[0].set_xticks(range(len(feats)), feats, rotation=35, ha="right", fontsize=7)
    axes[0].set_title(
        "eta^2: share of each one-step residual a feature explains\n"
        "(variable: its share of the residual)",
        fontsize=9,
    )
    fig.colorbar(im, ax=axes[0])
    top = loc.top
    ax = axes[1]
    if top is not None:
        i = loc.variables.index(top["variable"])
        x, y = loc.features[top["feature"]], loc.residual[:, i]
        ax.scatter(x, y, s=4, alpha=0.3, color="tab:gray")
        edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
        if len(np.unique(x)) <= max(3, bins // 2):
            centers = np.unique(x)
            means = [y[x == c].mean() for c in centers]
        else:
            idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
            centers = [x[idx == b].mean() for b in range(len(edges) - 1) if np.any(idx == b)]
            means = [y[idx == b].mean() for b in range(len(edges) - 1) if np.any(idx == b)]
        ax.plot(centers, means, "o-", color="tab:red", label="bin means")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(top["feature"])
        ax.set_ylabel(f"one-step residual of {top['variable']}")
        ax.set_title(f"most telling: eta^2 = {top['eta2']:.2f} (measured - simulated)", fontsize=9)
        ax.legend()
    fig.tight_layout()
    return fig


def _chain(res: Residuals, episode: int, horizon: int):
    """Back-to-back k-step windows of one episode: (starts, predictions)."""
    rows = np.flatnonzero(res.episode == episode)
    order = rows[np.argsort(res.start[rows])]
    chosen, next_start = [], 0
    for r in order:
        if res.start[r] >= next_start:
            chosen.append(r)
            next_start = res.start[r] + horizon
    return chosen


def trajectories(
    obs: np.ndarray,
    dt: float,
    before: Residuals,
    after: Residuals,
    episodes,
    names,
    horizon: int,
    title: str,
) -> plt.Figure:
    """Measured, simulated-before and simulated-after, the simulator restarted from the
    measured state every k steps (dots), for a few held-out episodes."""
    episodes = list(episodes)
    n = len(names)
    fig, axes = plt.subplots(
        n, max(len(episodes), 1), figsize=(5.5 * max(len(episodes), 1), 1.9 * n), squeeze=False
    )
    for col, e in enumerate(episodes):
        t = np.arange(obs.shape[1]) * dt
        for i, name in enumerate(names):
            ax = axes[i, col]
            ax.plot(t, obs[e, :, i], color="k", lw=1.2, label="measured")
            for res, color, label in (
                (before, "tab:red", "simulated before"),
                (after, "tab:blue", "simulated after"),
            ):
                # every window of the chain in one line, NaN between windows: one artist
                # instead of one per window keeps drawing the figure cheap
                chain = _chain(res, e, horizon)
                starts = res.start[chain]
                idx = starts[:, None] + np.arange(horizon + 1)
                tt = np.c_[t[idx], np.full(len(chain), np.nan)].ravel()
                yy = np.c_[
                    obs[e, starts, i], res.predicted[chain, :, i], np.full(len(chain), np.nan)
                ]
                ax.plot(tt, yy.ravel(), color=color, lw=1.0, label=label)
                ax.plot(t[starts], obs[e, starts, i], ".", color="k", ms=3)
            ax.set_ylabel(name)
            if i == 0:
                ax.set_title(f"{title}: episode {e}", fontsize=9)
                if col == 0:
                    ax.legend(fontsize=7)
        axes[-1, col].set_xlabel("time (s)")
    fig.tight_layout()
    return fig


def candidates(rows: list[dict], base_error: float, selected: set[str]) -> plt.Figure:
    """Held-out error of every candidate fitted alone (round 1)."""
    rows = sorted(rows, key=lambda r: r["heldout_error"])
    labels = [
        f"{r['name']}@{r['target']}"
        + (f"={next(iter(r['params'].values()))}" if effect_type(r["name"]).shifts_actions else "")
        for r in rows
    ]
    fig, ax = plt.subplots(figsize=(7, 0.28 * len(rows) + 1.2))
    colors = ["tab:green" if f"{r['name']}@{r['target']}" in selected else "tab:gray" for r in rows]
    ax.barh(range(len(rows)), [r["heldout_error"] for r in rows], color=colors)
    ax.axvline(base_error, color="tab:red", lw=1, label="simulator as it is")
    ax.set_yticks(range(len(rows)), labels, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel("held-out k-step error (normalized RMSE)")
    ax.set_title("each candidate effect fitted alone (green: selected)", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def gaps(rows: list[dict]) -> plt.Figure:
    """Return on the training simulator and on the plant, policy trained before/after."""
    fig, ax = plt.subplots(figsize=(5, 3.4))
    methods = [r["method"] for r in rows]
    x = np.arange(len(rows))
    ax.bar(x - 0.18, [r["sim_return"] for r in rows], 0.34, label="its simulator")
    ax.bar(x + 0.18, [r["real_return"] for r in rows], 0.34, label="the plant")
    ax.set_xticks(x, methods)
    ax.set_ylabel("return")
    ax.set_title("PODS: sim2real gap before and after the correction", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def correlation_matrix(correlations: list[dict]) -> plt.Figure | None:
    """The correlations between the named effects' fitted parameters (result.correlations:
    pairs of parameters of different effects) as a matrix: red and blue near +-1 are
    parameters the data trade against each other, a cross where they cannot be told apart.
    None with fewer than two parameters (nothing to correlate)."""
    names = list(dict.fromkeys(n for r in correlations for n in (r["a"], r["b"])))
    if len(names) < 2:
        return None
    index = {n: i for i, n in enumerate(names)}
    matrix = np.full((len(names), len(names)), np.nan)  # parameters of one effect: not given
    np.fill_diagonal(matrix, 1.0)
    for r in correlations:
        i, j = index[r["a"]], index[r["b"]]
        matrix[i, j] = matrix[j, i] = r["rho"]
    size = 2.5 + 0.55 * len(names)
    fig, ax = plt.subplots(figsize=(size + 1.2, size))
    image = ax.imshow(matrix, cmap="RdBu_r", vmin=-1.0, vmax=1.0)
    for r in correlations:
        i, j = index[r["a"]], index[r["b"]]
        for a, b in ((i, j), (j, i)):
            mark = " x" if r["inseparable"] else ""
            ax.text(b, a, f"{r['rho']:.2f}{mark}", ha="center", va="center", fontsize=7)
    ax.set_xticks(range(len(names)), names, rotation=35, ha="right", fontsize=7)
    ax.set_yticks(range(len(names)), names, fontsize=7)
    ax.set_title("correlation of the fitted parameters (x: not separable)", fontsize=9)
    fig.colorbar(image, ax=ax, shrink=0.8)
    fig.tight_layout()
    return fig
