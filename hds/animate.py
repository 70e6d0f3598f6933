"""A side-by-side animation (GIF) of one policy on the simulator and on the real plant."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FuncAnimation, PillowWriter  # noqa: E402


def pole_positions(obs: np.ndarray, names: tuple[str, ...], length: float = 0.6):
    """Cart x and pole tip (x, z) over time from observations [T, n_obs] (hinge = 0 is up)."""
    x = obs[:, names.index("q_slider")] if "q_slider" in names else np.zeros(len(obs))
    theta = obs[:, names.index("q_hinge")]
    return x, x + length * np.sin(theta), length * np.cos(theta)


def animate(
    sim_obs, real_obs, names, dt: float, path: Path, titles=("simulator", "real plant")
) -> Path:
    fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
    tracks = [pole_positions(o, names) for o in (sim_obs, real_obs)]
    span = max(1.0, max(float(np.abs(t[0]).max()) for t in tracks) + 0.8)
    artists = []
    for ax, title in zip(axes, titles):
        ax.set_xlim(-span, span)
        ax.set_ylim(-0.8, 0.8)
        ax.set_aspect("equal")
        ax.axhline(0, color="0.7", lw=1)
        ax.set_title(title)
        (cart,) = ax.plot([], [], "s", ms=14, color="tab:blue")
        (pole,) = ax.plot([], [], "-", lw=4, color="tab:brown")
        artists.append((cart, pole))
    label = fig.suptitle("")

    def frame(t):
        for (cart, pole), (x, tip_x, tip_z) in zip(artists, tracks):
            cart.set_data([x[t]], [0.0])
            pole.set_data([x[t], tip_x[t]], [0.0, tip_z[t]])
        label.set_text(f"t = {t * dt:.2f} s")
        return [a for pair in artists for a in pair] + [label]

    anim = FuncAnimation(fig, frame, frames=len(sim_obs), blit=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.gif")
    anim.save(tmp, writer=PillowWriter(fps=max(1, round(1 / dt))))
    plt.close(fig)
    tmp.replace(path)
    return path


def animate_run(
    run_dir: Path, method: str | None = None, seed_index: int = 0, out_dir: Path | None = None
) -> Path:
    """One episode of a finished run's policy (`method`, default the run's own; the
    seed_index-th run of its batch) on the simulator it trained on beside the run's plant,
    animated into out_dir (default: the run's plots/)."""
    from hds.policy import evaluate, load_policy

    run_dir = Path(run_dir)
    policy = load_policy(run_dir, method=method)
    if seed_index:
        policy = load_policy(run_dir, method=policy.method, **policy.config.runs()[seed_index])
    sim = evaluate(policy, episodes=1, plant=policy.training_plant())
    real = evaluate(policy, episodes=1)
    return animate(
        sim.episodes.obs[0],
        real.episodes.obs[0],
        policy.obs_names,
        policy.dt,
        Path(out_dir or run_dir / "plots") / f"{policy.method}_sim_vs_real.gif",
        titles=(
            f"simulator: return {sim.returns[0]:.0f}",
            f"{policy.config.real.plant} plant: return {real.returns[0]:.0f}",
        ),
    )
