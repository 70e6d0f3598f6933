"""A side-by-side animation (GIF) of one policy on the simulator and on the real plant: rendered
by MuJoCo's own renderer where OpenGL works headless (EGL or OSMesa: hds.render), else drawn as
a stick figure of the model's geoms with matplotlib."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from hds.envs.system import ASSETS, resolve_xml, state_names
from hds.utils.runtime import pyplot


def model_of(names: tuple[str, ...], xml: str | None = None) -> mujoco.MjModel:
    """The MJCF to draw: `xml` when given, else the shipped asset whose observation names are
    `names` (the names are the data contract)."""
    return mujoco.MjModel.from_xml_path(str(model_path(names, xml)))


def model_path(names: tuple[str, ...], xml: str | None = None) -> Path:
    """The file of `model_of`'s MJCF."""
    if xml is not None:
        return Path(resolve_xml(xml))
    for path in sorted(ASSETS.glob("*.xml")):
        model = mujoco.MjModel.from_xml_path(str(path))
        if tuple(state_names(model)) == tuple(names):
            return path
    raise ValueError(
        f"no shipped MJCF has the observations {list(names)}: pass xml= (the simulator's "
        "sim.xml) to draw a custom model"
    )


def geom_segments(model: mujoco.MjModel, obs: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    """[T, G, 2, 3]: the two ends, in world coordinates, of every geom on a moving body over
    time, from MuJoCo's forward kinematics at the observed q (capsules and cylinders along
    their axis; other shapes are a point)."""
    columns = [names.index(n) for n in state_names(model)[: model.nq]]
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] != 0]
    long = (int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_CYLINDER))
    half = np.array([model.geom_size[g, 1] if model.geom_type[g] in long else 0.0 for g in geoms])
    data = mujoco.MjData(model)
    out = np.zeros((len(obs), len(geoms), 2, 3))
    for t, q in enumerate(np.asarray(obs)[:, columns]):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        centre = data.geom_xpos[geoms]
        axis = data.geom_xmat[geoms].reshape(-1, 3, 3)[:, :, 2] * half[:, None]
        out[t] = np.stack([centre - axis, centre + axis], axis=1)
    return out


def project(points: np.ndarray) -> np.ndarray:
    """[..., 3] -> [..., 2]: the x-z plane, with an oblique view of y where the motion leaves
    that plane (the Furuta pendulum's arm)."""
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    if np.ptp(y) < 1e-6:
        return np.stack([x, z], axis=-1)
    return np.stack([x - 0.5 * y, z - 0.3 * y], axis=-1)


def animate(
    sim_obs,
    real_obs,
    names,
    dt: float,
    path: Path,
    titles=("simulator", "real plant"),
    xml: str | None = None,
    renderer: str = "auto",
) -> Path:
    """A GIF of two episodes side by side: rendered by MuJoCo (`renderer` "auto": where OpenGL
    works headless, hds.render), else (or with "stick") the model's kinematic tree (its geoms)
    drawn with matplotlib."""
    if renderer not in ("auto", "stick"):
        raise ValueError(f"renderer={renderer!r}: choose 'auto' (MuJoCo's, else) or 'stick'")
    xml_path = model_path(tuple(names), xml)
    model = mujoco.MjModel.from_xml_path(str(xml_path))
    segments = [geom_segments(model, o, tuple(names)) for o in (sim_obs, real_obs)]
    if renderer == "auto":
        from hds.render import camera, render_gif

        columns = [list(names).index(n) for n in state_names(model)[: model.nq]]
        qpos = [np.asarray(o)[:, columns] for o in (sim_obs, real_obs)]
        view = camera(np.concatenate([s.reshape(-1, 3) for s in segments]))
        if render_gif(xml_path, qpos, titles, dt, path, view) is not None:
            return path
    plt = pyplot()  # matplotlib on first use
    from matplotlib.animation import FuncAnimation, PillowWriter

    tracks = [project(s) for s in segments]
    points = np.concatenate([t.reshape(-1, 2) for t in tracks])
    lo, hi = points.min(axis=0) - 0.2, points.max(axis=0) + 0.2
    fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
    artists = []
    for ax, title in zip(axes, titles):
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.axhline(0, color="0.7", lw=1)
        ax.set_title(title)
        lines = [
            ax.plot([], [], "o-", lw=4, ms=5, color="tab:brown")[0]
            for _ in range(tracks[0].shape[1])
        ]
        artists.append(lines)
    label = fig.suptitle("")

    def frame(t):
        for lines, track in zip(artists, tracks):
            for line, seg in zip(lines, track[t]):
                line.set_data(seg[:, 0], seg[:, 1])
        label.set_text(f"t = {t * dt:.2f} s")
        return [a for lines in artists for a in lines] + [label]

    anim = FuncAnimation(fig, frame, frames=len(sim_obs), blit=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.gif")
    anim.save(tmp, writer=PillowWriter(fps=max(1, round(1 / dt))))
    plt.close(fig)
    tmp.replace(path)
    return path


def animate_episodes(sim, real, names, plant: str, dt: float, path: Path, xml: str) -> Path:
    """The first episode of `sim` and of `real` (hds.real.Episodes from the same initial
    state; observations named `names`) side by side, titled with their returns."""
    return animate(
        sim.obs[0],
        real.obs[0],
        names,
        dt,
        path,
        titles=(
            f"simulator: return {sim.returns[0]:.4g}",
            f"{plant} plant: return {real.returns[0]:.4g}",
        ),
        xml=xml,
    )
