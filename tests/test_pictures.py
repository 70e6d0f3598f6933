"""Pictures: the sim-vs-real GIF rendered by MuJoCo where OpenGL works headless, the stick
figure where it does not; the discovery report as one self-contained HTML page."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from hds import render
from hds.animate import animate

NAMES = ("q_slider", "q_hinge", "qd_slider", "qd_hinge")


def episodes(steps: int = 8):
    sim = np.zeros((steps, len(NAMES)))
    sim[:, 0] = np.linspace(-0.4, 0.4, steps)  # the cart moves, the pole tips
    sim[:, 1] = np.linspace(0.0, 0.8, steps)
    real = sim.copy()
    real[:, 1] *= -1
    return sim, real


def frames(gif) -> list[np.ndarray]:
    image = Image.open(gif)
    out = []
    for i in range(image.n_frames):
        image.seek(i)
        out.append(np.asarray(image.convert("RGB"), dtype=float))
    return out


@pytest.fixture
def fresh_backends(monkeypatch):
    """No memory of which OpenGL backend worked in this process."""
    monkeypatch.setattr(render, "_working", [])
    monkeypatch.setattr(render, "_failed", set())


def test_without_opengl_the_gif_is_the_stick_figure(tmp_path, monkeypatch, fresh_backends):
    monkeypatch.setenv("MUJOCO_GL", "disable")  # MuJoCo without any GL: the child fails
    gif = animate(*episodes(), NAMES, 0.1, tmp_path / "stick.gif")
    shots = frames(gif)
    assert len(shots) == 8 and shots[0].shape == (320, 800, 3)  # matplotlib's 8 x 3.2 in
    assert render._failed == {"disable"}
    assert not np.array_equal(shots[0], shots[-1])  # the figure moves


def test_mujoco_renders_frames_where_opengl_works(tmp_path, fresh_backends):
    sim, real = episodes()
    gif = animate(sim, real, NAMES, 0.1, tmp_path / "rendered.gif", ("sim", "plant"))
    if not render._working:
        pytest.skip(f"no headless OpenGL here (tried {sorted(render._failed)}): stick figure")
    shots = frames(gif)
    band = 36  # the titles' strip
    assert len(shots) == 8 and shots[0].shape == (render.HEIGHT + band, 2 * render.WIDTH, 3)
    for shot in shots:
        for panel in (shot[band:, : render.WIDTH], shot[band:, render.WIDTH :]):
            assert panel.std() > 5.0  # not blank: the model is drawn
    first, last = shots[0][band:], shots[-1][band:]
    assert np.abs(first - last).mean() > 0.5  # it moves
    left, right = shots[-1][band:, : render.WIDTH], shots[-1][band:, render.WIDTH :]
    assert np.abs(left - right).mean() > 0.5  # the pole tips one way on the sim, the other real


def test_the_renderer_is_chosen_by_name():
    with pytest.raises(ValueError, match="renderer='vtk'"):
        animate(*episodes(2), NAMES, 0.1, "unused.gif", renderer="vtk")


def test_the_discovery_report_is_logged_to_wandb_as_media(tmp_path):
    """A page (report.html), each figure as an image, the named effects and their
    correlations as tables: not markdown in a <pre>."""
    import json
    import time

    import matplotlib.pyplot as plt

    from hds.logger import RunLogger
    from hds.plots import save
    from hds.utils.html import markdown_page
    from tests.conftest import make_config, wandb_records

    report = tmp_path / "discovery"
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    save(fig, report / "plots" / "errors_heldout.png")
    text = "# Report\n\n| effect |\n| --- |\n| coulomb |\n\n![e](plots/errors_heldout.png)\n"
    (report / "report.html").write_text(markdown_page(text, report, "report"))
    effect = {
        "name": "coulomb_friction",
        "target": "slider",
        "params": {"force": 20.4},
        "ci95": {"force": [18.8, 22.1]},
        "explained_fraction": 0.97,
    }
    pair = {"a": "coulomb_friction@slider.force", "b": "x.y", "rho": -0.4, "inseparable": False}
    (report / "report.json").write_text(
        json.dumps({"missing_effects": [effect], "correlations": [pair]})
    )
    cfg = make_config("logger=wandb", "logger.mode=offline")
    logger = RunLogger(cfg, tmp_path, "pods_cl+corrected", cfg.runs(), console=False)
    logger.start(0)
    logger.log_discovery("discovery_report", report)
    logger.close()

    def logged() -> dict:  # {key: {field: value}}: W&B records media as an item per field
        out = {}
        for records in wandb_records(tmp_path).values():
            for r in records:
                for item in r.history.item if r.HasField("history") else ():
                    if len(item.nested_key) == 2:
                        key, field = item.nested_key
                        out.setdefault(key, {})[field] = json.loads(item.value_json)
        return out

    deadline = time.monotonic() + 60  # W&B's service writes the offline file after finish()
    while len(found := logged()) < 4 and time.monotonic() < deadline:
        time.sleep(0.5)
    logged = found
    assert logged["discovery_report"]["_type"] == "html-file"
    assert logged["discovery_report/errors_heldout"]["_type"] == "image-file"
    table = logged["discovery_report/named_effects"]
    assert table["_type"] == "table-file" and table["nrows"] == 1
    files = next(tmp_path.glob("wandb/offline-run-*/files"))
    rows = json.loads((files / table["path"]).read_text())["data"]
    assert rows == [["coulomb_friction", "slider", "force", 20.4, 18.8, 22.1, 0.97]]
    assert logged["discovery_report/correlations"]["nrows"] == 1
    page = (files / logged["discovery_report"]["path"]).read_text()
    assert "<td>coulomb</td>" in page and "data:image/png;base64," in page
