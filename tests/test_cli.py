"""Nothing silent, part two (issue 41): every command answers bad input in one line on stderr,
naming the key or file and the fix, with exit status 1 and no traceback; one command-line
style and installed scripts (issue 36). The bad files and values are generated here; every
case fails before anything compiles, so most run in process through the commands' own entry
functions, wrapped as the commands wrap them (hds.utils.cli)."""

from __future__ import annotations

import errno
import logging
import os
import re
import subprocess
import sys
import tomllib

import numpy as np
import pytest
from hydra import compose as hydra_compose
from hydra import initialize_config_dir

from hds import commands
from hds.config import CONF_DIR, compose
from hds.data.format import Dataset, save
from hds.utils import cli
from tests.conftest import ROOT

OBS = ("q_slider", "q_hinge", "qd_slider", "qd_hinge")  # the cart-pole's (env=cartpole_balance)
ACT = ("slide",)


def one_line(capsys, main, *args) -> str:
    """Run main(*args) as a command runs it; the one line it printed on stderr (asserted)."""
    with pytest.raises(SystemExit) as ended:
        with cli.one_line_errors():
            main(*args)
    assert ended.value.code == 1
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err
    return lines[0]


# --- hds.discover on bad data ----------------------------------------------------------------


def dataset(episodes=4, steps=30, **changes) -> Dataset:
    rng = np.random.default_rng(0)
    fields = {
        "obs": rng.normal(0, 0.1, (episodes, steps + 1, 4)),
        "actions": rng.uniform(-1, 1, (episodes, steps, 1)),
        "dt": 0.04,
        "obs_names": OBS,
        "action_names": ACT,
    }
    return Dataset(**(fields | changes))


def npz(path, **arrays):
    np.savez(path, **arrays)
    return path


def good_arrays():
    d = dataset()
    return {"obs": d.obs, "actions": d.actions, "dt": np.array(d.dt)}


HEADER = "episode,t," + ",".join(OBS) + ",u_slide"


def empty(path):
    path.write_bytes(b"")
    return path


def csv_text(path, header=HEADER, rows=None):
    rows = rows or [
        f"{e},{k * 0.04},0,0,0,0,{'0' if k < 3 else ''}" for e in (0, 1) for k in (0, 1, 2, 3)
    ]
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


def truncated(path):
    good = save(dataset(), path.with_name("whole.npz")).read_bytes()
    path.write_bytes(good[: len(good) // 2])
    return path


def unequal_episodes(path):
    rows = [f"0,{k * 0.04},0,0,0,0,{'0' if k < 5 else ''}" for k in range(6)]
    rows += [f"1,{k * 0.04},0,0,0,0,{'0' if k < 3 else ''}" for k in range(4)]
    return csv_text(path, rows=rows)


BAD_DATA = {  # case: (file maker, a fragment the line must hold besides the file's name)
    "empty npz": (lambda p: empty(p), "is empty (0 bytes)"),
    "truncated npz": (truncated, "truncated or corrupt"),
    "wrong keys": (
        lambda p: npz(p, observations=np.zeros((2, 3, 4)), u=np.zeros((2, 2, 1)), dt=0.04),
        "lacks the key(s) ['obs', 'actions']",
    ),
    "2-D observations": (
        lambda p: npz(p, **good_arrays() | {"obs": np.zeros((31, 4))}),
        "it must be [episodes, T+1, n_obs]",
    ),
    "NaN observation": (
        lambda p: save(
            dataset(obs=np.where(np.arange(4 * 31 * 4).reshape(4, 31, 4) == 9, np.nan, 0.1)), p
        ),
        "non-finite value(s)",
    ),
    "inf action": (
        lambda p: save(dataset(actions=np.full((4, 30, 1), np.inf)), p),
        "non-finite value(s)",
    ),
    "lengths disagree by one": (
        lambda p: npz(p, **good_arrays() | {"actions": np.zeros((4, 31, 1))}),
        "check for an off-by-one",
    ),
    "dt zero": (lambda p: npz(p, **good_arrays() | {"dt": np.array(0.0)}), "must be a positive"),
    "dt negative": (
        lambda p: npz(p, **good_arrays() | {"dt": np.array(-0.04)}),
        "must be a positive",
    ),
    "dt an array": (
        lambda p: npz(p, **good_arrays() | {"dt": np.array([0.04, 0.04])}),
        "it must be one number",
    ),
    "a single step": (lambda p: save(dataset(steps=1), p), "too short to identify anything"),
    "csv header typo": (
        lambda p: csv_text(p.with_suffix(".csv"), header=HEADER.replace("episode", "episod")),
        "starts with the columns episode,t",
    ),
    "observations of the wrong width": (
        lambda p: save(dataset(obs=np.zeros((4, 31, 3)), obs_names=OBS[:3]), p),
        "this system needs 4",
    ),
    "names permuted": (
        lambda p: save(dataset(obs_names=OBS[::-1]), p),
        "in another order: reorder",
    ),
    "actions outside the control range": (
        lambda p: save(dataset(actions=np.full((4, 30, 1), 50.0)), p),
        "outside the actuator's control range",
    ),
    "unequal episodes": (
        lambda p: unequal_episodes(p.with_suffix(".csv")),
        "every episode needs the same number of rows",
    ),
    "a string array": (
        lambda p: npz(p, **good_arrays() | {"obs": np.full((4, 31, 4), "x")}),
        "it must hold real numbers",
    ),
    "a directory": (lambda p: p.mkdir() or p, "is a directory: give a dataset file"),
}


@pytest.fixture(scope="module")
def discover_main():
    import runpy

    return runpy.run_module("hds.discover.__main__")["run"]


def discover_config(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose("discover", overrides=list(overrides))


@pytest.mark.parametrize("case", list(BAD_DATA))
def test_discover_refuses_bad_data_in_one_line(case, discover_main, tmp_path, capsys):
    make, fragment = BAD_DATA[case]
    path = make(tmp_path / "data.npz")
    line = one_line(capsys, discover_main, discover_config(f"data={path}"), tmp_path)
    assert str(path) in line and fragment in line, line
    assert not (tmp_path / "config.yaml").exists()  # refused before the run wrote anything


# --- large data: every command that reads or records data estimates it first (hds.data.budget)


def past_the_limit(tmp_path):
    """A dataset of 104 recorded steps (4 episodes x 26): just past a limit of 100."""
    return save(dataset(episodes=4, steps=26), tmp_path / "data.npz")


def assert_refused(line: str, where: str, key: str, fix: str):
    """The refusal's one line: what holds how many steps, the limit's key, the memory and time
    it would need, the fix and the limit raised."""
    assert f"{where} holds " in line and f"more than {key} = 100" in line, line
    assert re.search(r"would need about [\d.]+ [MG]B of memory and \d+ (s|min|h)", line), line
    assert fix.lower() in line.lower() and f"raise {key}" in line, line


@pytest.mark.parametrize("key", ["data", "validation"])
def test_discover_refuses_data_past_max_steps_with_the_numbers(
    discover_main, key, tmp_path, capsys
):
    path = past_the_limit(tmp_path)
    small = save(dataset(episodes=2, steps=20), tmp_path / "small.npz")
    files = {"data": small, "validation": small} | {key: path}
    cfg = discover_config(*(f"{k}={v}" for k, v in files.items()), "discover.max_steps=100")
    line = one_line(capsys, discover_main, cfg, tmp_path)
    assert f"{key} = {path} holds 104 steps (4 episodes x 26)" in line
    assert_refused(line, f"{key} = {path}", "discover.max_steps", "resample it to a coarser dt")


def hydra_command(module: str, *overrides: str, tmp_path):
    """`python -m <module> <overrides>` in this process, as its __main__ runs it (Hydra's
    logging configures nothing), for a refusal that comes before anything compiles."""
    from hydra.core.global_hydra import GlobalHydra

    from tests.conftest import command_main

    def run():
        argv = sys.argv
        sys.argv = [module, *overrides, f"hydra.run.dir={tmp_path / 'run'}"]
        sys.argv += ["hydra.job_logging.root=null", "hydra.hydra_logging.root=null"]
        try:
            command_main(module)()
        finally:
            sys.argv = argv
            GlobalHydra.instance().clear()

    return run


@pytest.mark.parametrize(
    "overrides, key",
    [
        (["method=hds"], "dynamics.max_steps"),  # a learned model fitted on the data
        (["simulator=corrected"], "discover.max_steps"),  # gap discovery on the data
    ],
)
def test_run_refuses_dynamics_data_past_the_limit(overrides, key, tmp_path, capsys):
    path = past_the_limit(tmp_path)
    run = hydra_command(
        "hds.run", *overrides, f"dynamics.data={path}", f"{key}=100", tmp_path=tmp_path
    )
    line = one_line(capsys, run)
    assert f"dynamics.data = {path} holds 104 steps (4 episodes x 26)" in line
    assert_refused(line, f"dynamics.data = {path}", key, "resample it to a coarser dt")


def test_run_refuses_plant_data_past_the_limit_before_recording(tmp_path, capsys):
    overrides = ["method=hds", "dynamics.episodes=4", "dynamics.horizon=26"]
    run = hydra_command("hds.run", *overrides, "dynamics.max_steps=100", tmp_path=tmp_path)
    line = one_line(capsys, run)
    where = "the data recorded on the plant (dynamics.episodes x dynamics.horizon)"
    assert_refused(line, where, "dynamics.max_steps", "lower dynamics.episodes")


def test_loop_refuses_its_data_past_the_limit_before_round_0(tmp_path, capsys):
    """2 rounds of 1 + 1 episodes of the task's 26 steps: 104 steps to discover on."""
    overrides = ["loop.rounds=2", "loop.deploy_episodes=1", "loop.excitation_episodes=1"]
    overrides += ["env.task.horizon=26", "discover.max_steps=100"]
    line = one_line(capsys, hydra_command("hds.loop", *overrides, tmp_path=tmp_path))
    assert "holds 104 steps (4 episodes x 26)" in line
    assert_refused(
        line,
        "the loop's data (loop.rounds = 2, 2 episodes each)",
        "discover.max_steps",
        "lower loop.rounds",
    )
    assert not (tmp_path / "run" / "rounds").exists()  # nothing trained or recorded


def test_dynamics_command_refuses_its_data_past_the_limit(tmp_path, capsys):
    from tests.conftest import command_main

    args = ["dynamics.episodes=4", "dynamics.horizon=26", "dynamics.max_steps=100"]
    line = one_line(capsys, command_main("hds.dynamics"), args)
    where = "the data recorded on the plant (dynamics.episodes x dynamics.horizon)"
    assert_refused(line, where, "dynamics.max_steps", "lower dynamics.episodes")


def test_a_multirun_refuses_its_jobs_data_past_the_limit_before_launching_any(
    tmp_path, capsys, monkeypatch
):
    """One job's data past dynamics.max_steps (the other's within it): no job launches."""
    path = past_the_limit(tmp_path)
    argv = ["-m", "method=hds", f"dynamics.data={path}", "dynamics.max_steps=100,1000"]
    monkeypatch.setattr(sys, "argv", ["hds.run", *argv, f"hydra.sweep.dir={tmp_path / 'sweep'}"])
    with pytest.raises(SystemExit) as ended:
        commands.before_hydra()
    assert ended.value.code == 1
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 2 and "Traceback" not in err, lines
    assert lines[0].startswith("error: job 0 (dynamics.max_steps=100): dynamics.data = ")
    assert_refused(lines[0], f"dynamics.data = {path}", "dynamics.max_steps", "resample it")
    assert "1 of 2 jobs refused, none launched" in lines[1]
    assert not (tmp_path / "sweep").exists()


def test_discovery_itself_refuses_data_past_the_limit_and_shows_progress(caplog):
    """The API's `discover` (the loop's and the corrected simulator's discovery too) refuses
    data past discover.max_steps before it compiles; within it, its estimate and stages go to
    the log (`Progress`, checked on its own: a discovery run is not cheap)."""
    from hds.data.budget import DISCOVERY, Progress
    from hds.discover import DiscoverConfig, discover

    env = compose([]).env
    with pytest.raises(ValueError, match="the data holds 104 steps, more than discover.max_"):
        discover(dataset(episodes=4, steps=26), env, DiscoverConfig(max_steps=100))
    with caplog.at_level(logging.INFO, logger="hds"):
        progress = Progress(DISCOVERY, 2_000_000, logging.getLogger("hds"))
        progress("the gap located")
    first, stage = (r.getMessage() for r in caplog.records[-2:])
    assert first.startswith("gap discovery on 2000000 recorded steps: about 10.8 GB of memory")
    assert stage.startswith("gap discovery: the gap located (0 s so far, about ")


def test_discover_takes_good_data_past_its_checks(tmp_path):
    """The same checks pass the data they should (the refusals above are not a blanket)."""
    import runpy

    from hds.config import validate

    load_data = runpy.run_module("hds.discover.__main__")["load_data"]
    path = save(dataset(), tmp_path / "data.npz")
    data, validation = load_data(validate(discover_config(f"data={path}")))
    assert data.obs.shape == (4, 31, 4) and validation is None


# --- configuration values --------------------------------------------------------------------

BAD_VALUES = {  # overrides: fragments of the line
    ("real.friction_gap=1e39",): ("real.friction_gap = 1e+39 is beyond float32", "smaller"),
    ("real=brax", "sweep.friction_gap=[1,1e39]"): ("sweep.friction_gap[1] = 1e+39", "float32"),
    ("seed=9223372036854775807",): (
        "seed = 9223372036854775807 is out of range",
        "[0, 2147483647]",
    ),
    ("seed=-1",): ("seed = -1 is out of range", "[0, 2147483647]"),
    ("seed=2147483647", "seeds=2"): ("seed = 2147483647 is out of range", "[0, 2147483646]"),
    ("eval_seed=99999999999",): ("eval_seed = 99999999999 is out of range", "[0, 2147483647]"),
    ("env=custom",): ("env.xml has no value (???)", "env.xml=<value> (an MJCF file's path)"),
    ("algo.improve_in=closed_loop", "algo.grad_window=101"): (
        "algo.grad_window = 101 is longer than the task's horizon (env.task.horizon = 100)",
        "give at most 100",
    ),
    ("anneal.horizon_start=500",): ("anneal.horizon_start = 500 is longer", "give at most 100"),
}


@pytest.mark.parametrize("overrides", list(BAD_VALUES), ids=" ".join)
def test_bad_values_are_refused_in_one_line_naming_the_key(overrides, capsys):
    line = one_line(capsys, compose, list(overrides))
    assert all(fragment in line for fragment in BAD_VALUES[overrides]), line


@pytest.mark.parametrize(
    "mjcf, fragment",
    [
        ('<mujoco>\n<worldbody>\n<body>\n<geom size="0.1"\n</body></worldbody></mujoco>', "XML"),
        ('<mujoco><worldbody><geom type="nonsense" size="1"/></worldbody></mujoco>', "nonsense"),
    ],
)
def test_a_malformed_mjcf_is_named_with_its_key_and_file(mjcf, fragment, tmp_path, capsys):
    xml = tmp_path / "robot.xml"
    xml.write_text(mjcf)
    line = one_line(capsys, compose, [f"env.xml={xml}"])
    assert line.startswith("error: invalid config: env.xml: ") and str(xml) in line
    assert fragment in line and "fix" in line, line


# --- multiruns: every job checked before any is launched --------------------------------------

S = ("env.backend=analytic", "algo.epochs=2", "algo.chunk=2", "logger=none")


def test_a_multirun_with_bad_values_launches_nothing_and_names_each(tmp_path, capsys, monkeypatch):
    argv = ["-m", *S, "real.friction_gap=-1,2,-3", f"hydra.sweep.dir={tmp_path}"]
    monkeypatch.setattr(sys, "argv", ["hds.run", *argv])
    with pytest.raises(SystemExit) as ended:
        commands.before_hydra()
    assert ended.value.code == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 3, lines
    assert lines[0].startswith("error: job 0 (real.friction_gap=-1): invalid config: ")
    assert "real.friction_gap = -1.0 is out of range" in lines[0]
    assert lines[1].startswith("error: job 2 (real.friction_gap=-3)")
    assert "2 of 3 jobs refused, none launched" in lines[2]
    assert not any(tmp_path.iterdir())  # no job directory


def test_a_multirun_of_good_values_passes_and_a_single_run_is_not_expanded():
    assert commands.invalid_jobs(["-m", *S, "real.friction_gap=0,2", "seed=0,1"]) == []
    assert commands.invalid_jobs(["-m", *S, "algo.step_size=interval(0.01,0.1)"]) == []
    (line,) = commands.invalid_jobs([*S, "real.friction_gap=0,2"])  # a sweep without -m
    assert line.startswith("real.friction_gap=0,2 sweeps several values: add -m")


def test_a_sweep_the_experiment_sets_is_checked_as_the_command_lines(tmp_path):
    """hydra.sweeper.params in an experiment sweeps as a command line's sweep does (the lab
    study sweeps its methods so): its jobs are checked, and a key given on the command line
    replaces the experiment's sweep of it, as Hydra's basic sweeper does."""
    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "own_sweep.yaml").write_text(
        "# @package _global_\nhydra:\n  sweeper:\n    params:\n      real.friction_gap: 0,-1\n"
    )
    argv = ["-m", "--config-dir", str(tmp_path), *S, "+experiment=own_sweep"]
    lines = commands.invalid_jobs([*argv, "seed=0,1"])
    assert [line.split(":")[0] for line in lines[:-1]] == [
        "job 2 (real.friction_gap=-1 seed=0)",
        "job 3 (real.friction_gap=-1 seed=1)",
    ]
    assert "2 of 4 jobs refused" in lines[-1]
    assert commands.invalid_jobs([*argv, "real.friction_gap=2"]) == []


def test_an_experiment_that_makes_itself_a_multirun_has_its_own_sweep_checked(tmp_path):
    """Without -m and without a sweep on the command line, an experiment that sets hydra.mode:
    MULTIRUN launches its own sweep: its jobs are checked, not the one job its defaults
    compose (the lab study's swing-ups were refused so, for the default method)."""
    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "own_multirun.yaml").write_text(
        "# @package _global_\nhydra:\n  mode: MULTIRUN\n  sweeper:\n    params:\n"
        "      real.friction_gap: 0,-1\n"
    )
    argv = ["--config-dir", str(tmp_path), *S, "+experiment=own_multirun"]
    lines = commands.invalid_jobs(argv)
    assert lines[0].startswith("job 1 (real.friction_gap=-1): invalid config: "), lines
    assert "1 of 2 jobs refused" in lines[-1]
    assert commands.invalid_jobs([*argv, "real.friction_gap=2"]) == []


@pytest.mark.parametrize(
    "override, fragments",
    [
        ("env=nonexist", ("Could not find 'env/nonexist'", "cartpole_balance")),
        ("algo.epochs=abc", ("algo.epochs", "abc")),
    ],
)
def test_hydras_own_composition_errors_are_one_line(override, fragments, capsys, monkeypatch):
    monkeypatch.setattr(sys, "argv", ["hds.run", override])
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    with pytest.raises(SystemExit) as ended:
        commands.before_hydra()
    assert ended.value.code == 1
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("error: ") and all(f in line for f in fragments), line


# --- hds.evaluate, hds.export, hds.report, hds.dynamics: the key=value commands ------------


@pytest.fixture(scope="module")
def mains():
    from tests.conftest import command_main

    return {name: command_main(f"hds.{name}") for name in ("evaluate", "export", "report")}


@pytest.mark.parametrize(
    "command, args, fragment",
    [
        ("evaluate", ["run=x", "eval_episodes=0"], "eval_episodes = 0 evaluates nothing"),
        ("evaluate", ["run=x", "eval_seed=99999999999"], "eval_seed = 99999999999 must lie in"),
        ("evaluate", ["run=x", "eval_seed=-1"], "eval_seed = -1 must lie in [0, 2147483647]"),
        ("evaluate", ["eval_episodes=4"], "run=... is required"),
        ("export", ["run=x", "seed=one"], "seed='one' must be a int"),
        ("export", ["run=x", "colour=red"], "unknown key 'colour'; the keys are run,"),
        ("report", ["outputs/x"], "'outputs/x' is not key=value"),
        ("report", ["dir=x", "gif_plant=x4"], "add gif=true"),
    ],
)
def test_the_key_value_commands_refuse_bad_arguments_in_one_line(
    command, args, fragment, mains, capsys
):
    line = one_line(capsys, mains[command], args)
    assert fragment in line, line


def test_a_missing_run_directory_is_one_line(mains, tmp_path, capsys):
    line = one_line(capsys, mains["export"], [f"run={tmp_path / 'none'}"])
    assert str(tmp_path / "none") in line


# --- write failures -------------------------------------------------------------------------


@pytest.mark.parametrize(
    "code, fix",
    [
        (errno.ENOSPC, "free space on that disk"),
        (errno.EROFS, "writable file system"),
        (errno.EACCES, "choose a directory you can write to"),
    ],
)
def test_a_write_failure_is_one_line_with_the_file_and_the_fix(code, fix, capsys):
    def write():
        raise OSError(code, os.strerror(code), "/runs/x/checkpoints/4")

    line = one_line(capsys, write)
    assert line.startswith("error: /runs/x/checkpoints/4: ") and fix in line, line


def test_writing_under_a_file_is_one_line(tmp_path, capsys):
    from hds.utils.io import atomic_write_json

    (tmp_path / "a_file").write_text("")
    line = one_line(capsys, atomic_write_json, tmp_path / "a_file" / "out" / "x.json", {})
    assert "a_file" in line and "fix the path" in line, line


def test_a_full_disk_at_a_checkpoint_is_one_error_without_orbaxs_log(tmp_path, caplog):
    """Orbax's threads log a traceback per failed write (hundreds of lines on a full disk)
    before the save raises; the save raises ENOSPC naming the directory, and drops that log.
    (The real thing, on a 1.5 MB tmpfs: one line, and the run resumed once space was freed.)"""
    import absl.logging  # noqa: F401  (the logger Orbax writes to)
    import jax.numpy as jnp

    from hds.checkpoint import Checkpoints

    ckpt = Checkpoints(tmp_path / "ckpt")

    def full_disk(*args, **kwargs):
        logging.getLogger("absl").error("_SignalingThread.run() raised an exception: ...")
        raise ValueError("RESOURCE_EXHAUSTED: Failed to write: No space left on device [28]")

    def other_failure(*args, **kwargs):
        logging.getLogger("absl").error("a failure Orbax explains in its log")
        raise RuntimeError("not a full disk")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(ckpt.manager, "save", other_failure)
        with pytest.raises(RuntimeError, match="not a full disk"):
            ckpt.save(2, {"w": jnp.zeros(3)}, {})
        assert "a failure Orbax explains in its log" in caplog.text  # kept for a real failure
        patch.setattr(ckpt.manager, "save", full_disk)
        with pytest.raises(OSError) as raised:
            ckpt.save(2, {"w": jnp.zeros(3)}, {})
        assert raised.value.errno == errno.ENOSPC
        assert cli.describe(raised.value).startswith(f"{tmp_path / 'ckpt'}: No space left")
        assert "_SignalingThread" not in caplog.text
    again = Checkpoints(tmp_path / "ckpt")  # started again, with space: saving works
    again.save(2, {"w": jnp.zeros(3)}, {})
    assert again.latest() == 2
    again.close()


# --- the convention itself ------------------------------------------------------------------


def test_debug_shows_the_traceback_and_a_bug_keeps_it(monkeypatch):
    monkeypatch.setenv("HYDRA_FULL_ERROR", "0")  # recorded, so that the test leaves it unset

    def refused(argv):
        raise ValueError(f"bad value, argv {argv}")

    with pytest.raises(ValueError, match=r"argv \['x=1'\]"):  # --debug: the traceback
        cli.run(refused, ["x=1", "--debug"])
    assert os.environ["HYDRA_FULL_ERROR"] == "1"
    monkeypatch.delenv("HYDRA_FULL_ERROR")
    with pytest.raises(KeyError):  # not a user error: never hidden
        cli.run(lambda argv: {}["missing"], [])


# --- installed scripts ------------------------------------------------------------------------


def test_every_command_is_installed_as_a_script_whose_entry_imports():
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert set(scripts) == set(commands.SCRIPTS)
    assert {"hds-run", "hds-loop", "hds-discover", "hds-evaluate", "hds-export"} <= set(scripts)
    assert "hds-report" in scripts
    import importlib
    import importlib.util

    for script, target in scripts.items():
        module, _, function = target.partition(":")
        assert callable(getattr(importlib.import_module(module), function)), script
        assert importlib.util.find_spec(commands.SCRIPTS[script]) is not None, script
    import hds

    assert callable(hds.evaluate_policy) and callable(hds.export_policy)


def test_the_api_s_old_names_of_evaluate_and_export_still_work_with_a_warning():
    import hds
    from hds import policy

    for old, new in (("evaluate", "evaluate_policy"), ("export", "export_policy")):
        with pytest.warns(DeprecationWarning, match=f"use hds.{new}"):
            assert getattr(hds, old) is getattr(hds, new)
        with pytest.warns(DeprecationWarning, match=f"use {new}"):
            assert getattr(policy, old) is getattr(policy, new)
    with pytest.raises(AttributeError):
        policy.evaluation  # noqa: B018


def test_a_script_runs_its_command_and_answers_in_one_line(tmp_path):
    """hds-export as installed (its entry function), in a process of its own."""
    code = "import sys; from hds.commands import export; sys.argv[0] = 'hds-export'; export()"
    proc = subprocess.run(
        [sys.executable, "-c", code, f"run={tmp_path / 'none'}"],
        cwd=ROOT,
        env={k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]
    assert str(tmp_path / "none") in proc.stderr
