"""The few lines per method a sweep ends with (hds.story), and its figure: from rows as
hds.report reads them, with gap discovery's named effects beside the plant's truth."""

from __future__ import annotations

import json

import pytest

from hds import story
from hds.report import aggregate, build, sweep_story


def row(method, seed, real, plant="coulomb_friction@slider", sim=-3.0, job="0"):
    return {
        "method": method,
        "plant": plant,
        "friction_gap": 1.0,
        "seed": seed,
        "sim_return": sim,
        "real_return": real,
        "gap": sim - real,
        "solved_sim": True,
        "solved_real": real >= -10,
        "job": job,
    }


def rows_of_a_sweep():
    rows = [row("oracle", s, r) for s, r in enumerate((-3.0, -5.0))]
    rows += [row("pods_cl", s, r) for s, r in enumerate((-8.0, -12.0))]
    rows += [row("pods_cl+corrected", s, r, sim=-4.0) for s, r in enumerate((-4.0, -4.0))]
    rows += [row("pods_cl", s, -20.0, plant="gain@slide") for s in (0, 1)]
    return rows


def test_the_story_ranks_methods_with_intervals_solved_seeds_and_cost():
    text = story.story(aggregate(rows_of_a_sweep()))
    blocks = text.split("\n\n")
    assert len(blocks) == 2  # one per plant
    friction = next(b for b in blocks if "coulomb_friction@slider" in b.splitlines()[0])
    lines = friction.splitlines()
    assert lines[0] == (
        "On the plant coulomb_friction@slider: best oracle, real return -4 [-16.7, 8.71]"
    )
    # best on the plant first (the oracle and the corrected simulator tie at -4), worst last
    methods = [line.split(" (")[0] for line in lines[1:] if not line.startswith("  ")]
    assert methods[-1] == "pods_cl"  # the worst last
    pods = lines.index("pods_cl (2 seeds)")
    assert lines[pods + 1] == "  real return -10 [-35.4, 15.4]   sim2real gap 7 [-18.4, 32.4]"
    # 1 of 2 seeds solves on the plant (-8 >= -10 > -12); real cost 10 over the oracle's 4
    assert lines[pods + 2] == (
        "  solved by 2/2 on the simulator, 1/2 on the plant; cost 2.50x the oracle's"
    )
    oracle_lines = lines[lines.index("oracle (2 seeds)") :][:3]
    assert "the oracle's" not in "\n".join(oracle_lines)  # no ratio to itself
    gain = next(b for b in blocks if b is not friction)
    assert "cost" not in gain  # no oracle on that plant: no ratio


def test_discovery_is_told_beside_the_plants_truth():
    truth = [
        {"name": "coulomb_friction", "target": "slider", "params": {"force": 40.0}},
        {"name": "actuator_gain", "target": "slide", "params": {"gain": 0.5}},
    ]
    named = [
        {
            "name": "coulomb_friction",
            "target": "slider",
            "params": {"force": 38.2},
            "ci95": {"force": [36.0, 40.4]},
        },
        {"name": "sensor_bias", "target": "x", "params": {"bias": 0.01}, "ci95": {}},
    ]
    found = [
        {
            "label": "pods_cl+corrected",
            "plant": "coulomb_friction@slider",
            "friction_gap": 1.0,
            "effects": named,
            "truth": truth,
            "warnings": ["the held-out error grew"],
        }
    ]
    text = story.story(aggregate(rows_of_a_sweep()), found)
    assert (
        "  discovery named coulomb_friction@slider force 38.2 [36, 40.4] (plant: 40); "
        "sensor_bias@x bias 0.01 (not in the plant); missed: actuator_gain@slide gain 0.5"
    ) in text.splitlines()
    assert "  discovery warned: the held-out error grew" in text.splitlines()
    # only beneath the method and plant that ran it
    assert text.count("discovery named") == 1
    assert story.named_beside_truth([], []) == "nothing (the plant has no effect either)"
    assert story.named_beside_truth(named[:1], None).endswith("were not recorded)")


def test_the_story_figure_has_a_bar_and_its_interval_per_method():
    summary = [e for e in aggregate(rows_of_a_sweep()) if e["plant"] != "gain@slide"]
    fig = story.figure(summary, "title")
    returns, gaps = fig.axes
    assert [t.get_text() for t in returns.get_yticklabels()] == [
        "pods_cl\n-10 [-35.4, 15.4]",
        "pods_cl+corrected\n-4 [-4, -4]",
        "oracle\n-4 [-16.7, 8.71]",
    ]  # the best on top, each with its mean and interval
    assert [t.get_text() for t in gaps.get_yticklabels()][0] == "7 [-18.4, 32.4]"
    assert len(returns.patches) == len(gaps.patches) == 3
    assert [p.get_width() for p in returns.patches] == [-10.0, -4.0, -4.0]
    assert returns.get_xscale() == "linear"
    failed = aggregate(rows_of_a_sweep()[:4] + [row("pods", s, -1500.0) for s in (0, 1)])
    assert story.figure(failed).axes[0].get_xscale() == "symlog"  # -1500 beside -4 and -10


def test_a_sweep_directory_is_told_with_its_discovery_and_figure(tmp_path):
    """sweep_story reads the jobs' summary.json files (as a multirun leaves them), takes the
    plant's truth from where the job recorded it, and draws summary.png."""
    rows = rows_of_a_sweep()[:6]
    named = [
        {
            "name": "coulomb_friction",
            "target": "slider",
            "params": {"force": 20.4},
            "ci95": {"force": [18.8, 22.1]},
        }
    ]
    truth = [{"name": "coulomb_friction", "target": "slider", "params": {"force": 20.0}}]
    for job, method in enumerate(("oracle", "pods_cl", "pods_cl+corrected")):
        summary = {
            "name": "sim2real_friction",
            "rows": [  # a job's rows: its plant is in "real"
                {k: v for k, v in r.items() if k not in ("plant", "friction_gap", "job")}
                for r in rows
                if r["method"] == method
            ],
            "history": {method: {k: [[1.0], [1.0]] for k in ("return", "loss", "step_size")}},
            "discovery": {"effects": named, "warnings": []} if "corrected" in method else {},
            "real": {
                "plant": "mujoco",
                "name": "coulomb_friction@slider",
                "friction_gap": 1.0,
                "effects": truth,
            },
        }
        (tmp_path / str(job)).mkdir()
        (tmp_path / str(job) / "summary.json").write_text(json.dumps(summary))
    text, figure = sweep_story(tmp_path)
    assert figure == tmp_path / "plots" / "summary.png" and figure.stat().st_size > 10_000
    assert "pods_cl+corrected (2 seeds)" in text
    assert "  discovery named coulomb_friction@slider force 20.4 [18.8, 22.1] (plant: 20)" in text
    report = build(tmp_path).read_text()  # hds.report tells the same story, and draws it
    assert text in report and "![report_summary](plots/report_summary.png)" in report
    assert (tmp_path / "plots" / "report_summary.png").is_file()


@pytest.mark.parametrize("oracle_return", [0.0, float("nan")])
def test_no_cost_ratio_against_an_oracle_that_costs_nothing_or_diverged(oracle_return):
    rows = [row("oracle", s, oracle_return) for s in (0, 1)] + [row("pods_cl", 0, -5.0)]
    assert "the oracle's" not in story.story(aggregate(rows))
