"""The lab study's domain randomization (experiments/lab_study/, make study-lab): over the
lab family's own distribution (hds.real.lab.randomization), as the study's configs state it."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from hds.real import lab

# the study's tasks (the Makefile's LAB_TASKS); a Furuta task takes the Furuta family's configs
TASKS = ["cartpole_balance", "cartpole_swingup", "furuta_balance", "furuta_swingup"]
CONF = Path(__file__).resolve().parents[1] / "experiments" / "lab_study" / "conf" / "experiment"


def _family(task: str) -> str:
    """The suffix of a task's study configs, as the Makefile picks it."""
    return "_furuta" if task.startswith("furuta") else ""


@pytest.mark.parametrize("family", sorted(lab.FAMILIES))
def test_every_draw_lies_inside_the_family_s_randomization(family):
    """Every continuous value a draw has, on the simulator's dynamics, lies inside its range;
    what a randomized simulator cannot draw per rollout (a discrete value, the sensors) is left
    out, and no range is empty or reversed."""
    ranged = {(e["name"], e["target"]): e["ranges"] for e in lab.randomization(family)}
    assert ranged
    for k in range(20):
        truth = lab.draw(family, k)
        for e in truth["effects"]:
            if e["name"] in lab.OBSERVED or e["name"] in ("action_delay", "cogging_torque"):
                assert (e["name"], e["target"]) not in ranged
                continue
            ranges = ranged[(e["name"], e["target"])]
            for param, (low, high) in ranges.items():
                assert low < high and low <= e["params"][param] <= high, (k, e, param)


@pytest.mark.parametrize(
    "family, config", [("lab_cartpole", "lab_study"), ("lab_furuta", "lab_study_furuta")]
)
def test_the_study_randomizes_over_the_family_s_own_distribution(family, config):
    stated = yaml.safe_load((CONF / f"{config}.yaml").read_text())["dr"]["effects"]
    assert stated == lab.randomization(family)


@pytest.mark.parametrize("task", TASKS)
def test_every_task_of_the_study_builds_its_system_on_the_study_s_backend(task):
    """`make study-lab`'s loop config for each task, composed as the Makefile composes it,
    gives a backend that can run the task's system (make_env's checks, made before anything
    compiles: a Furuta on the cart-pole's analytic backend failed every job of its sweep). The
    sweeps' configs take their env from the same family config as the loop's."""
    from hds.config import compose
    from hds.envs import make_env

    family = _family(task)
    cfg = compose(
        [f"env={task}", f"+experiment=[lab_study_loop{family},lab_task_{task}]"],
        config_dirs=[CONF.parent],
    )
    assert cfg.env.name == task
    make_env(cfg.env)


@pytest.mark.parametrize("task", TASKS)
def test_the_study_offers_discovery_every_library_effect_a_draw_hides(task):
    """A lab draw changes every body's mass, centre of mass and inertia and gives every
    joint's dry friction a static peak. Discovery is offered each effect of its library that
    the draws hide and the law that carries a static peak (breakaway_friction, a refinement of
    Coulomb's), in the one-shot's and the loop's configs alike: without the inertial ones a
    mass scale stands in for them, and the misfit it leaves hides a step of delay. The config
    states its list whole, so it is checked to hold every default candidate too."""
    from hds.config import compose
    from hds.effects.library import default_candidates

    family = _family(task)
    hidden = {
        e["name"]
        for k in range(10)
        for e in _hidden_library_effects(_study_report().family_of(task), k)
    }
    assert {"mass_scale", "com_scale", "inertia_scale", "action_delay"} <= hidden
    offered = hidden | {"breakaway_friction"} | set(default_candidates())
    for config, method in (
        (f"lab_study{family}", ["method=pods_corrected"]),
        (f"lab_study_loop{family}", []),
    ):
        cfg = compose(
            [f"env={task}", f"+experiment=[{config},lab_task_{task}]", *method],
            config_dirs=[CONF.parent],
        )
        assert offered <= set(cfg.discover.effects), config


def _hidden_library_effects(family: str, k: int) -> list[dict]:
    """The effects draw k of a lab family hides that discovery's library has as candidates."""
    from hds.effects.library import candidate_effects

    return [e for e in lab.draw(family, k)["effects"] if e["name"] in candidate_effects()]


def _swept_methods(config: str) -> list[str]:
    """The methods a study sweep config runs, each a job (its own or its parent's list)."""
    while True:
        data = yaml.safe_load((CONF / f"{config}.yaml").read_text())
        methods = data.get("hydra", {}).get("sweeper", {}).get("params", {}).get("method")
        if methods:
            return methods.split(",")
        config = next(d for d in data["defaults"] if isinstance(d, str) and d.startswith("lab_"))


@pytest.mark.parametrize("task", TASKS)
def test_every_job_of_the_study_s_sweeps_composes(task):
    """Each job `make study-lab` sweeps (the per-draw and the shared sweep, with each of its
    methods) composes and passes validation: a job whose config is refused fails only once
    the sweep reaches it, possibly an hour into the study."""
    from hds.config import compose

    family = _family(task)
    jobs = [
        (config, method)
        for config in (f"lab_study{family}", f"lab_study{family}_shared")
        for method in _swept_methods(config)
    ]
    assert len(jobs) == 4
    for config, method in jobs:
        cfg = compose(
            [f"env={task}", f"+experiment=[{config},lab_task_{task}]", f"method={method}"],
            config_dirs=[CONF.parent],
        )
        assert cfg.env.name == task, (config, method)


@pytest.mark.parametrize("task", TASKS)
def test_the_study_s_loops_start_from_the_shared_sweep_s_raw_simulator_job(task, tmp_path):
    """The Makefile starts each draw's loop, with and without HDS's hybrid, from the shared
    sweep's first job (shared/0: the raw simulator on draw 0), whose training must be the
    loops' round 0: a loop refused there would fail only after the sweeps, an hour in."""
    from omegaconf import OmegaConf

    from hds import loop, rundir
    from hds.config import compose

    family = _family(task)
    shared = f"lab_study{family}_shared"
    raw = compose(
        [f"env={task}", f"+experiment=[{shared},lab_task_{task}]", "real.draw=0"]
        + [f"method={_swept_methods(shared)[0]}"],
        config_dirs=[CONF.parent],
    )
    assert raw.simulator == "nominal"
    ran = tmp_path / "shared" / "0"
    (ran / "checkpoints" / raw.algo.name).mkdir(parents=True)
    OmegaConf.save(OmegaConf.structured(raw), ran / rundir.CONFIG, resolve=True)
    (ran / "summary.json").write_text("{}")
    makefile = (CONF.parents[3] / "Makefile").read_text()
    assert makefile.count("loop.start_from=$$out/shared/0") == 2
    for extra in ([], ["dynamics=residual"]):
        ours = compose(
            [f"env={task}", f"+experiment=[lab_study_loop{family},lab_task_{task}]"]
            + ["real.draw=2", f"loop.start_from={ran}", *extra],
            config_dirs=[CONF.parent],
        )
        source = loop.round_zero_source(ours)
        assert source == ran / "checkpoints" / raw.algo.name


def _make_study_lab(tmp_path, tasks: str, draws: str) -> list[list[str]]:
    """The commands `make study-lab` runs for `tasks` and `draws` (LAB_DRAWS), each as its
    arguments, recorded by a stand-in for the venv's python that runs nothing."""
    import subprocess

    bin_dir, log = tmp_path / "bin", tmp_path / "calls"
    bin_dir.mkdir()
    # The loops run two at a time: a lock (mkdir is atomic) keeps each record on its own line.
    (bin_dir / "python").write_text(
        '#!/bin/sh\nuntil mkdir "$LOG.lock" 2>/dev/null; do sleep 0.01; done\n'
        'printf "%s\\037" "$@" >> "$LOG"\necho >> "$LOG"\nrmdir "$LOG.lock"\n'
    )
    (bin_dir / "python").chmod(0o755)
    root = CONF.parents[3]
    subprocess.run(
        ["make", "-s", "-o", ".venv/.installed", "study-lab", f"BIN={bin_dir}"]
        + [f"LAB_TASKS={tasks}", f"LAB_DRAWS={draws}", f"LAB_RUN={tmp_path / 'lab'}"],
        cwd=root,
        env={"PATH": "/usr/bin:/bin", "LOG": str(log)},
        check=True,
        capture_output=True,
    )
    return [line.split("\x1f")[:-1] for line in log.read_text().splitlines()]


def _composed(args: list[str], *extra: str):
    """The config a recorded hds.run or hds.loop command composes (its sweep's values as
    given; Hydra's own settings and the command-line flags left out)."""
    from hds.config import compose

    flags = {"-m", "--config-dir", str(CONF.parent.relative_to(CONF.parents[3]))}
    overrides = [a for a in args[2:] if a not in flags and not a.startswith("hydra.")]
    return compose([*overrides, *extra], config_dirs=[CONF.parent])


def test_make_study_lab_runs_the_draws_it_is_given(tmp_path):
    """`make study-lab LAB_DRAWS=...` runs each task on those draws, none other: the per-draw
    sweep over all of them, the shared sweep trained on the first and evaluated on each other
    one (eval_plants), and per draw a loop and a hybrid loop started from the shared sweep's
    raw-simulator job; then the report. Every job's config composes (hds is judged on draws
    that are not the study's)."""
    calls = _make_study_lab(tmp_path, "cartpole_balance furuta_swingup", "7 3 12")
    lab = tmp_path / "lab"
    assert calls[-1] == ["experiments/lab_study/report.py", str(lab)]
    for task, family in (("cartpole_balance", "lab_cartpole"), ("furuta_swingup", "lab_furuta")):
        out = lab / task
        ours = [c for c in calls if any(a.startswith(f"hydra.sweep.dir={out}/") for a in c)]
        per_draw, shared = ours
        assert "real.draw=7,3,12" in per_draw and f"hydra.sweep.dir={out}/per_draw" in per_draw
        for method in _swept_methods(f"lab_study{_family(task)}_shared"):
            cfg = _composed(shared, f"method={method}")
            assert cfg.real.family == family and cfg.real.draw == 7, method
            plants = {k: (v.family, v.draw) for k, v in cfg.eval_plants.items()}
            assert plants == {"d3": (family, 3), "d12": (family, 12)}, method
        loops = [c for c in calls if c[:2] == ["-m", "hds.loop"] and f"env={task}" in c]
        ran = set()  # each draw's pair runs side by side: in either order
        for args in loops:
            cfg = _composed(args)
            kind = "loop" if cfg.dynamics.model == "none" else "hybrid"
            assert cfg.dynamics.model in ("none", "residual")
            assert cfg.loop.start_from == str(out / "shared" / "0")
            assert f"hydra.run.dir={out}/{kind}/d{cfg.real.draw}" in args
            ran.add((cfg.real.draw, kind))
        assert len(loops) == 6 and ran == {(k, x) for k in (7, 3, 12) for x in ("loop", "hybrid")}


def test_make_study_lab_s_own_draws_are_0_to_4_or_0_to_2_for_a_swing_up(tmp_path):
    calls = _make_study_lab(tmp_path, "furuta_balance cartpole_swingup", "")
    sweeps = [c for c in calls if c[:2] == ["-m", "hds.run"]]
    assert [next(a for a in c if a.startswith("real.draw=")) for c in sweeps] == [
        "real.draw=0,1,2,3,4",
        "real.draw=0",
        "real.draw=0,1,2",
        "real.draw=0",
    ]
    assert sum("eval_plants.d4.draw=4" in c for c in sweeps) == 1  # the balance task's
    loops = [next(a for a in c if a.startswith("real.draw=")) for c in calls if "hds.loop" in c]
    draws = [f"real.draw={k}" for k in (0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 0, 0, 1, 1, 2, 2)]
    assert loops == draws  # a draw's pair side by side, the draws one after the other


def _study_report():
    """experiments/lab_study/report.py as a module (the study's script, not a package)."""
    return _study_script("report")


def _study_script(name: str):
    """experiments/lab_study/<name>.py as a module."""
    import importlib.util

    path = CONF.parents[1] / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"lab_study_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("family", sorted(lab.FAMILIES))
def test_the_report_judges_every_library_effect_a_draw_hides_against_its_truth(family):
    """What discovery may name of a draw's hidden library effects (a centre of mass and an
    inertia among them) is read against the draw's own value, never as "not in the plant"; an
    effect the draw does not hide (a lag) has no truth."""
    truth_values = _study_report().truth_values
    truth = lab.draw(family, 1)
    hidden = _hidden_library_effects(family, 1)
    assert {"com_scale", "inertia_scale"} <= {e["name"] for e in hidden}
    for e in hidden:
        if e["name"] == "action_delay" and not e["params"]["steps"]:
            continue  # no delay: no effect to judge against
        values = truth_values(truth, e["name"], e["target"])
        assert values is not None, e
        assert all(values[p] == e["params"][p] for p in values), e
    target = "motor" if family == "lab_furuta" else "slide"
    assert truth_values(truth, "actuator_lag", target) is None


def test_the_report_names_each_quantity_of_a_breakaway_friction_against_its_truth():
    """A breakaway friction is judged as its sliding and static levels (force + peak, its
    interval the ends' sums) against the draw's Stribeck friction, each quantity named; a
    one-parameter effect reads as before."""
    report = _study_report()
    truth = lab.draw("lab_cartpole", 0)
    (stribeck,) = [
        e["params"]
        for e in truth["effects"]
        if e["name"] == "stribeck_friction" and e["target"] == "slider"
    ]
    named = [
        {
            "name": "breakaway_friction",
            "target": "slider",
            "params": {"force": 12.0, "peak": 4.0, "velocity": 0.05},
            "ci95": {"force": [8.0, 16.0], "peak": [0.0, 9.0], "velocity": [0.01, 0.2]},
        },
        {"name": "actuator_lag", "target": "slide", "params": {"time_constant": 0.06}},
    ]
    text = report.named_vs_truth(named, truth)
    friction, lag = text.split("; ")
    assert friction == (
        f"breakaway_friction@slider force 12 [8, 16] vs {stribeck['force']:.3g}, "
        f"static 16 [8, 25] vs {stribeck['static']:.3g}, "
        f"velocity 0.05 [0.01, 0.2] vs {stribeck['velocity']:.3g}"
    )
    assert lag == "actuator_lag@slide 0.06 [-, -] vs not in the plant"


def test_the_study_counts_a_hybrid_win_only_where_the_loop_left_room():
    """A draw has room where the oracle beats the loop beyond both intervals; the hybrid's
    win counts there. A loop at the oracle's level leaves none, whatever the hybrid does."""
    report = _study_report()
    oracle = [10.0, 10.2, 9.8]
    data = {
        0: {"oracle": {"costs": oracle}, "loop": {"costs": [14.0, 14.3, 13.7]},
            "hybrid": {"costs": [10.1, 10.0, 10.2]}},  # room, and the hybrid takes it
        1: {"oracle": {"costs": oracle}, "loop": {"costs": [14.0, 14.3, 13.7]},
            "hybrid": {"costs": [14.1, 13.9, 14.0]}},  # room, not taken
        2: {"oracle": {"costs": oracle}, "loop": {"costs": [10.1, 9.9, 10.0]},
            "hybrid": {"costs": [9.0, 9.1, 8.9]}},  # no room: the loop is at the oracle's
    }  # fmt: skip
    lines = report.room_for_a_model(data)
    assert "Draws with room: 2 of 3; the hybrid beats the loop on 1 of them." in lines[1]
    rows = [line.split(" | ") for line in lines if line.startswith("| ") and "---" not in line]
    assert [(r[2], r[4].rstrip(" |")) for r in rows[1:]] == [
        ("yes", "yes"),
        ("yes", "no"),
        ("no", "yes"),
    ]


def test_the_signal_comparison_reads_a_finished_run_without_running_it(tmp_path, monkeypatch):
    """experiments/lab_study/one_shot_signal.py: a (draw, signal) whose run directory holds a
    summary is read, not run again; its row holds the draw's delay from the truth, what was
    named against it and the plant seconds of every record (episodes x horizon x step)."""
    import json
    import subprocess

    from omegaconf import OmegaConf

    from hds.real import lab

    module = _study_script("one_shot_signal")
    monkeypatch.setattr(subprocess, "run", lambda *a, **k: pytest.fail("ran a finished run"))
    run_dir = tmp_path / "furuta_balance_100_prbs"
    run_dir.mkdir()
    delay = {"name": "action_delay", "target": "motor", "params": {"steps": 1}}
    summary = {
        "discovery": {"effects": [delay], "episodes": 64},
        "rows": [{"real_return": -1.31, "sim_return": -1.23}],
    }
    (run_dir / "summary.json").write_text(json.dumps(summary))
    env = {"timestep": 0.002, "frames_per_step": 10}
    OmegaConf.save(
        OmegaConf.create({"env": env, "dynamics": {"horizon": 100}}), run_dir / "config.yaml"
    )
    found = module.run("furuta_balance", 100, "prbs", tmp_path)
    line = module.row("furuta_balance", 100, "prbs", found).strip("| ").split(" | ")
    truth = [e for e in lab.draw("lab_furuta", 100)["effects"] if e["name"] == "action_delay"]
    assert line[:3] == ["100", "prbs", str(truth[0]["params"]["steps"] if truth else 0)]
    assert line[3].startswith("action_delay@motor 1")
    assert line[4:] == ["-1.31 (-1.23)", "128"]  # 64 episodes x 100 steps x 20 ms


def _scale(name: str, target: str, value: float) -> dict:
    key = "gain" if name == "actuator_gain" else "scale"
    return {"name": name, "target": target, "params": {key: value}}


def test_the_rigid_body_measure_counts_what_a_model_predicts_not_its_scales_one_by_one():
    """A pendulum 10% heavier (its mass and inertia together) moves as one with a motor 1/1.1
    as strong: a model naming that gain leaves none of the rigid-body error, where judging
    the scales one by one calls the gain spurious and the mass missed. A gain of 1.1 instead
    is worse than naming nothing; friction, named or not, does not enter."""
    report = _study_report()
    rigid = report._RIGID
    truth = [_scale("mass_scale", "pole", 1.1), _scale("coulomb_friction", "hinge", 0.5)]
    assert rigid.error_left("pendulum.xml", truth, [_scale("actuator_gain", "torque", 1 / 1.1)])[
        "hinge"
    ] == pytest.approx(0.0, abs=1e-6)
    assert rigid.error_left("pendulum.xml", truth, [])["hinge"] == pytest.approx(1.0)
    assert (
        rigid.error_left("pendulum.xml", truth, [_scale("actuator_gain", "torque", 1.1)])["hinge"]
        > 1.5
    )
    # the report's column: per joint, on a lab draw's truth
    draw = lab.draw("lab_furuta", 4)
    line = report.rigid_left(draw, [_scale("inertia_scale", "arm", 2.8)])
    arm, pendulum = (float(part.split()[1]) for part in line.split(", "))
    assert line.startswith("arm ") and ", pendulum " in line
    assert 0.0 < arm < 0.5 and 0.0 < pendulum < 1.0


@pytest.mark.parametrize("task", ["cartpole_balance", "furuta_swingup"])
def test_the_out_of_library_comparison_gives_the_plant_the_draw_less_what_it_removes(task):
    """experiments/lab_study/out_of_library.py: its overrides compose into a plant with every
    effect of the draw, each parameter's value as drawn, less the removed ones, and no
    family (whose draw would put them back)."""
    from hds.config import compose

    module = _study_script("out_of_library")
    family = module.family_of(task)
    removed = "cogging_torque" if family == "lab_furuta" else "backlash"
    drawn = lab.effects(family, 7)
    assert any(e["name"] == removed for e in drawn)
    for without in ([], [removed]):
        cfg = compose(module.overrides(task, 7, "prbs", without), config_dirs=[CONF.parent])
        assert cfg.real.family == "" and cfg.dynamics.excitation == "prbs"
        got = [
            {"name": e.name, "target": e.target, "params": dict(e.params)} for e in cfg.real.effects
        ]
        assert got == [e for e in drawn if e["name"] not in without]
