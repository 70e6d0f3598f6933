"""A side-by-side animation (GIF) of one policy on the simulator and on the real plant."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FuncAnimation, PillowWriter  # noqa: E402

from hds.algo.pods import make_train  # noqa: E402
from hds.checkpoint import Checkpoints  # noqa: E402
from hds.config import load_config  # noqa: E402
from hds.envs import make_env  # noqa: E402
from hds.real import make_plant, rollout  # noqa: E402


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


def simulator_of(cfg, run_dir: Path):
    """The simulator a finished run's policy trained on (cfg.simulator)."""
    if cfg.simulator == "real":
        from hds.run import real_dynamics

        return real_dynamics(cfg)[0]
    if cfg.simulator == "corrected":  # the env config gap discovery wrote into the run
        from omegaconf import OmegaConf

        from hds.discover.retrain import env_config

        (path,) = (run_dir / "discovery" / "conf" / "env").glob("*.yaml")
        return make_env(env_config(OmegaConf.to_container(OmegaConf.load(path))))
    return make_env(cfg.env)


def animate_run(
    run_dir: Path, method: str | None = None, seed_index: int = 0, out_dir: Path | None = None
) -> Path:
    """Rebuild a finished run from its config.yaml and last checkpoint; animate one episode
    into out_dir (default: the run's plots/)."""
    from hds.run import method_name

    config_path = run_dir / "config.yaml"
    if not config_path.is_file():
        raise FileNotFoundError(
            f"{config_path} not found: give the directory of one run "
            "(a sweep's job directory), which holds config.yaml and checkpoints/"
        )
    cfg = load_config(config_path)
    env, plant = simulator_of(cfg, run_dir), make_plant(cfg.real, cfg.env)
    method = method or method_name(cfg)
    trainer = make_train(cfg, env)
    keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(cfg.seeds))
    like = jax.vmap(trainer.init, in_axes=(0, None))(keys, trainer.default_hparams)
    state, _ = Checkpoints(run_dir / "checkpoints" / method).restore(like)
    params = jax.tree.map(lambda x: x[seed_index], state.policy)
    act = jax.jit(trainer.policy.apply)
    q0, qd0 = (np.asarray(x)[None] for x in env.task.initial(jax.random.PRNGKey(cfg.eval_seed)))
    controller = lambda obs: np.asarray(act(params, jnp.asarray(obs, jnp.float32)))  # noqa: E731
    from hds.real.brax_plant import BraxPlant

    sim_eps = rollout(BraxPlant(env), env.task, q0, qd0, controller, env.task.horizon)
    real_eps = rollout(plant, env.task, q0, qd0, controller, env.task.horizon)
    return animate(
        sim_eps.obs[0],
        real_eps.obs[0],
        env.sim.obs_names,
        env.sim.dt,
        Path(out_dir or run_dir / "plots") / f"{method}_sim_vs_real.gif",
        titles=(
            f"simulator: return {sim_eps.returns[0]:.0f}",
            f"{cfg.real.plant} plant: return {real_eps.returns[0]:.0f}",
        ),
    )
