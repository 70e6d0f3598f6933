"""Episodes drawn by MuJoCo's own renderer (`mujoco.Renderer`), headless, into a GIF.

MuJoCo picks its OpenGL backend from MUJOCO_GL when it is first imported, and a process has
imported it long before a GIF is drawn (without MUJOCO_GL, on Linux: GLFW, which needs a
display). So the frames are rendered in a child process (`python -m hds.render JOB.npz`) with
MUJOCO_GL set: EGL (a GPU's, or Mesa's) or OSMesa (software; Debian: libosmesa6), the first
that works, remembered for the process. A machine with neither (the child fails or crashes:
a GL crash never takes the caller with it) gets None, and hds.animate draws its stick figure.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

log = logging.getLogger("hds")

BACKENDS = ("egl", "osmesa")  # tried in this order when MUJOCO_GL is not set
WIDTH, HEIGHT = 320, 240  # each panel's pixels
_working: list[str] = []  # the backend that rendered in this process (tried once each)
_failed: set[str] = set()


def backends() -> list[str]:
    """The OpenGL backends to try: MUJOCO_GL's alone where it is set, else EGL then OSMesa;
    the one that worked before first, those that failed left out."""
    chosen = os.environ.get("MUJOCO_GL")
    candidates = [chosen] if chosen else list(BACKENDS)
    return [b for b in _working if b in candidates] + [
        b for b in candidates if b not in _failed and b not in _working
    ]


def camera(points: np.ndarray, fovy: float = 45.0) -> dict:
    """A fixed free camera that sees every point ([N, 3], world) of both episodes: looking
    along +y at the middle of their bounding box (the x-z plane the cart-poles move in),
    slightly from above, far enough back for the box's larger side and a margin."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre = (lo + hi) / 2
    span = max(float(hi[0] - lo[0]) * HEIGHT / WIDTH, float(hi[2] - lo[2]), 0.2)
    distance = 0.6 * span / np.tan(np.radians(fovy) / 2) + 0.5 * float(hi[1] - lo[1])
    return {"lookat": centre, "distance": distance, "azimuth": 90.0, "elevation": -15.0}


def render_gif(
    xml: Path, qpos: list[np.ndarray], titles, dt: float, path: Path, view: dict
) -> Path | None:
    """Two episodes' joint positions (`qpos`: [T, nq] each, the model's qpos order) rendered
    side by side into the GIF at `path`, titled, at real time; None where no OpenGL works."""
    with tempfile.TemporaryDirectory() as tmp:
        job = Path(tmp) / "job.npz"
        np.savez(
            job,
            xml=str(xml),
            out=str(path),
            titles=np.array(list(titles)),
            dt=dt,
            sim=qpos[0],
            real=qpos[1],
            **{k: np.asarray(v, dtype=float) for k, v in view.items()},
        )
        for backend in backends():
            env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
            proc = subprocess.run(
                [sys.executable, "-m", "hds.render", str(job)],
                env=env,
                capture_output=True,
                text=True,
                timeout=600,
            )
            if proc.returncode == 0 and path.is_file():
                _working[:] = [backend]
                return path
            _failed.add(backend)
            last = (proc.stderr.strip().splitlines() or [f"exit code {proc.returncode}"])[-1]
            log.info("MuJoCo's renderer with MUJOCO_GL=%s did not work: %s", backend, last)
    return None


def _frames(job) -> list:
    """The child's work: every step of both episodes rendered and composed into RGB images."""
    import mujoco
    from PIL import Image, ImageDraw

    model = mujoco.MjModel.from_xml_path(str(job["xml"]))
    data = mujoco.MjData(model)
    renderer = mujoco.Renderer(model, HEIGHT, WIDTH)
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = job["lookat"]
    cam.distance, cam.azimuth, cam.elevation = (
        float(job["distance"]),
        float(job["azimuth"]),
        float(job["elevation"]),
    )
    titles, dt = [str(t) for t in job["titles"]], float(job["dt"])
    band = 36  # a strip above the panels for the titles and the time
    frames = []
    for t in range(len(job["sim"])):
        canvas = Image.new("RGB", (2 * WIDTH, HEIGHT + band), "white")
        draw = ImageDraw.Draw(canvas)
        for i, key in enumerate(("sim", "real")):
            data.qpos[:] = job[key][t]
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=cam)
            canvas.paste(Image.fromarray(renderer.render()), (i * WIDTH, band))
            draw.text((i * WIDTH + 6, 4), titles[i], fill="black")
        draw.text((6, 20), f"t = {t * dt:.2f} s", fill="black")
        frames.append(canvas)
    renderer.close()
    return frames


def main(job_path: str) -> None:
    job = dict(np.load(job_path))
    frames = _frames(job)
    out = Path(str(job["out"]))
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp.gif")
    duration = max(int(round(1000 * float(job["dt"]))), 20)  # GIF delays are 10 ms units
    frames[0].save(tmp, save_all=True, append_images=frames[1:], duration=duration, loop=0)
    tmp.replace(out)


if __name__ == "__main__":
    main(sys.argv[1])
