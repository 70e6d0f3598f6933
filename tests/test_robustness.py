"""Nothing lost, nothing silent (issue 18): a run directory remembers the configuration that
produced it and is locked while in use; a damaged checkpoint is skipped; NaN and inf are refused
in configs and data, written as null in results, and a run or sweep that produced nothing
finite or had a failed job exits non-zero; range errors print one line."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from hds import experiment, rundir
from hds.algo.pods import make_train_from_config
from hds.callbacks import StartChecks
from hds.checkpoint import Checkpoints
from hds.data import Dataset, validate
from hds.envs import make_env
from hds.gap import diverged, no_finite_result
from hds.utils.io import atomic_write_json, file_mode
from tests.conftest import CONF, ROOT, TINY, make_config, trained

# the issue's small budget S, smaller still: the tests' TINY (its programs) over 4 epochs
S = (*TINY, "algo.epochs=4")


def composed(*overrides: str):
    """The composed, unvalidated config `python -m hds.run` hands to main()."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def hds_run_cli(*args, cwd=ROOT) -> subprocess.CompletedProcess:
    env = {**os.environ, "WANDB_MODE": "offline"}
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.run(
        [sys.executable, "-m", "hds.run", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


# --- data lost or mixed --------------------------------------------------------------------


def test_a_rerun_with_other_settings_is_refused_naming_the_keys(tmp_path):
    out = tmp_path / "run"
    with rundir.claim(out, composed(*S)):
        (out / "checkpoints").mkdir()  # a run that trained some epochs, then was killed
    changed = composed(*S, "algo.step_size=0.3", "algo.hidden=[32]")
    with pytest.raises(rundir.RunDirectoryError) as refused:
        with rundir.claim(out, changed):
            pass
    message = str(refused.value)
    assert "algo.step_size: 0.02 -> 0.3" in message and "algo.hidden: [64, 64] -> [32]" in message
    assert "resume_changed=true" in message
    assert OmegaConf.load(out / "config.yaml").algo.step_size == 0.02  # the record is kept

    with rundir.claim(out, composed(*S, "algo.step_size=0.3", "resume_changed=true")):
        pass  # asked for explicitly: accepted, the old configuration kept beside it
    assert OmegaConf.load(out / "config.yaml").algo.step_size == 0.3
    assert OmegaConf.load(out / "config.1.yaml").algo.step_size == 0.02

    (out / "summary.json").write_text("{}")  # finished: never recomputed, so always refused
    with pytest.raises(rundir.RunDirectoryError, match="finished with another configuration"):
        with rundir.claim(out, composed(*S, "algo.step_size=0.5", "resume_changed=true")):
            pass


def test_a_refused_rerun_prints_one_line_and_keeps_hydras_record(tmp_path, capsys, monkeypatch):
    """The issue's command on a finished run's directory, through the command line."""
    from hds.commands import before_hydra

    out = tmp_path / "run"
    # refused at once: by what `python -m hds.run` calls before Hydra (in this process, as a
    # process of its own would only add its start-up), so before Hydra writes anything
    monkeypatch.setattr(
        sys, "argv", ["hds.run", *S, "real.friction_gap=-1", f"hydra.run.dir={out}"]
    )
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    with pytest.raises(SystemExit) as first:
        before_hydra()
    err = capsys.readouterr().err
    assert first.value.code == 1 and len(err.strip().splitlines()) == 1, err
    assert err.startswith("error: invalid config: real.friction_gap = -1.0")
    assert not out.exists()  # refused before Hydra wrote anything
    hydra_dir = out / ".hydra"
    hydra_dir.mkdir(parents=True)
    OmegaConf.save(composed(*S), hydra_dir / "config.yaml")  # as Hydra writes it
    with rundir.claim(out, composed(*S), hydra_dir):
        (out / "summary.json").write_text("{}")  # as if it had finished with these settings
    before = (out / ".hydra" / "config.yaml").read_text()
    second = hds_run_cli(*S, "algo.epochs=10", f"hydra.run.dir={out}")
    assert second.returncode == 1 and "Traceback" not in second.stderr
    assert "algo.epochs: 4 -> 10" in second.stderr
    assert (out / ".hydra" / "config.yaml").read_text() == before
    assert OmegaConf.load(out / "config.yaml").algo.epochs == 4


def test_a_second_run_on_a_directory_in_use_is_refused_at_once(tmp_path):
    cfg, hydra_dir = composed(*S), tmp_path / ".hydra"
    hydra_dir.mkdir()
    (hydra_dir / "overrides.yaml").write_text("[first]")
    with rundir.claim(tmp_path, cfg, hydra_dir):
        (hydra_dir / "overrides.yaml").write_text("[second]")  # Hydra writes before main()
        with pytest.raises(
            rundir.RunDirectoryError, match=rf"in use by another run \(pid {os.getpid()}\)"
        ):
            with rundir.claim(tmp_path, cfg, hydra_dir):
                pass
        assert (hydra_dir / "overrides.yaml").read_text() == "[first]"  # the first run's record
    with rundir.claim(tmp_path, cfg):  # free again once the first ended
        pass


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory):
    cfg = make_config(*S)
    env = make_env(cfg.env)
    out = tmp_path_factory.mktemp("uninterrupted")
    params, history = trained(cfg, env, out, "pods")
    return cfg, env, out, params, history


def test_a_trained_run_started_again_restores_its_policies_and_compiles_nothing(
    uninterrupted, tmp_path, monkeypatch
):
    """Its checkpoints hold every epoch: the state is restored into its shapes, and neither
    init nor the chunk is compiled (hds.loop's round 0 from loop.start_from does the same)."""
    from hds import experiment

    cfg, env, out, params, history = uninterrupted
    shutil.copytree(out / "checkpoints", tmp_path / "checkpoints")

    def refuse(*args, **kwargs):
        raise AssertionError("a trained run compiled its trainer")

    monkeypatch.setattr(experiment, "start_and_compile", refuse)
    restored, restored_history = trained(cfg, env, tmp_path, "pods")
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(restored), strict=True):
        np.testing.assert_array_equal(a, b)
    assert restored_history == history


# Orbax's asyncio loop may be collected before a callback of the failed read: "Event loop is
# closed", printed as an unraisable exception in some runs (the restore itself is checked below)
@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_corrupt_latest_checkpoint_falls_back_and_ends_identical(uninterrupted, tmp_path, caplog):
    cfg, env, out, params, history = uninterrupted
    shutil.copytree(out / "checkpoints", tmp_path / "checkpoints")
    latest = tmp_path / "checkpoints" / "pods" / str(cfg.algo.epochs)
    for data in latest.glob("state/**/d/*"):  # truncated, as by a full disk
        os.truncate(data, data.stat().st_size // 2)
    resumed, resumed_history = trained(cfg, env, tmp_path, "pods")
    assert f"checkpoint {latest} cannot be read" in caplog.text
    assert "resuming from checkpoint 2" in caplog.text
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(resumed)):
        np.testing.assert_array_equal(a, b)
    assert resumed_history == history


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # as above
def test_reading_past_a_corrupt_checkpoint_leaves_it_in_place(uninterrupted, tmp_path, caplog):
    """A reader (load_policy, the report's GIF) falls back as training does, but deletes
    nothing: only training writes that epoch again."""
    cfg, env, out, *_ = uninterrupted
    shutil.copytree(out / "checkpoints", tmp_path / "checkpoints")
    directory = tmp_path / "checkpoints" / "pods"
    for data in (directory / str(cfg.algo.epochs)).glob("state/**/d/*"):
        os.truncate(data, data.stat().st_size // 2)
    checkpoints = Checkpoints(directory)
    like = experiment.abstract_state(cfg, make_train_from_config(cfg, env))
    state, _ = checkpoints.restore(like)
    assert int(state.epoch[0]) == 2 and "reading checkpoint 2" in caplog.text
    assert checkpoints.latest() == cfg.algo.epochs  # still there
    checkpoints.close()


def test_a_checkpoint_of_another_network_is_named_as_such(uninterrupted):
    _, env, out, *_ = uninterrupted
    other = make_config(*S, "algo.hidden=[32]")
    trainer = make_train_from_config(other, env)
    one_run = jax.tree.map(lambda x: x[None], trainer.default_hparams)
    like = jax.eval_shape(jax.vmap(trainer.init), jax.random.PRNGKey(0)[None], one_run)
    checkpoints = Checkpoints(out / "checkpoints" / "pods")
    with pytest.raises(
        ValueError, match=r"another configuration.*Dense_0.bias \(1, 64\) -> \(1, 32\)"
    ):
        checkpoints.restore(like)
    checkpoints.close()


# --- silent acceptance -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "override, message",
    [
        ("real.friction_gap=inf", "real.friction_gap = inf is not a finite number"),
        ("noise.scale=inf", "noise.scale = inf is not a finite number"),
        ("env.task.q_spread=[nan,0.3]", r"env.task.q_spread\[0\] = nan is not a finite number"),
    ],
)
def test_non_finite_config_values_are_refused(override, message):
    with pytest.raises(ValueError, match=message):
        make_config(override)


def test_non_finite_results_are_written_as_null_with_a_flag(tmp_path):
    path = atomic_write_json(tmp_path / "s.json", {"rows": [{"sim_return": float("nan")}]})
    text = path.read_text()
    summary = json.loads(text, parse_constant=lambda c: pytest.fail(f"bare {c} in {text}"))
    assert summary == {"rows": [{"sim_return": None}], "non_finite": ["rows[0].sim_return"]}
    assert path.stat().st_mode & 0o777 == file_mode() != 0o600  # mkstemp's private mode


def test_a_diverging_simulator_is_reported_and_gives_no_finite_result(tmp_path, caplog):
    """A motor 1e30 times stronger in the simulator (the cart leaves float32's range in a
    step): every rollout's return is NaN."""
    huge = "env.effects=[{name:actuator_gain,target:slide,params:{gain:1e30}}]"
    summary = experiment.run(make_config(*S, huge), tmp_path).summary()
    assert "evaluation rollouts diverged to NaN or inf: 2 of 2 on the simulator" in caplog.text
    assert "training rollouts diverged in every epoch too, and were all skipped" in caplog.text
    assert no_finite_result(summary["rows"]).startswith("no finite result: every row (1)")
    written = json.loads((tmp_path / "summary.json").read_text())
    assert written["rows"][0]["sim_return"] is None and written["non_finite"]


def test_every_rollout_diverged_is_said_so():
    runs = [{"seed": 0}]
    lines = diverged("pods", runs, np.full((1, 3), np.nan), np.full((1, 3), np.inf))
    assert lines and "(every rollout): 3 of 3 on the simulator and 3 of 3 on the plant" in lines[0]
    assert diverged("pods", runs, np.zeros((1, 3)), np.zeros((1, 3))) == []
    read_back = [{"sim_return": None, "real_return": -1.0}]  # a finished run's summary.json
    assert no_finite_result(read_back) and not no_finite_result([{**read_back[0], "sim_return": 0}])


@pytest.fixture(scope="module")
def sim():
    return make_env(make_config("env.backend=analytic").env).sim


def _dataset(obs_value=0.1, action_value=1.0, episodes=8):
    obs = np.full((episodes, 6, 4), obs_value)
    return Dataset(obs, np.full((episodes, 5, 1), action_value), 0.04)


def test_data_values_that_overflow_the_simulator_are_refused(sim):
    with pytest.raises(ValueError, match=r"192 value\(s\) beyond 1.8e\+19, which overflow"):
        validate(_dataset(obs_value=1e300), sim)


def test_data_actions_outside_the_control_range_are_refused(sim):
    with pytest.raises(
        ValueError, match=r"40 of 40 actions lie outside .*\[-3, 3\], the data reach 3e\+04"
    ):
        validate(_dataset(action_value=3e4), sim)


def test_fitting_on_data_all_non_finite_says_every_episode_was_dropped():
    from hds.dynamics.training import fit

    cfg = make_config("env.backend=analytic", "dynamics=mlp")
    with pytest.raises(ValueError, match="all 8 episodes hold NaN or inf values"):
        fit(cfg.dynamics, make_env(cfg.env), _dataset(obs_value=1e300).obs, _dataset().actions)


# --- unclear crashes -------------------------------------------------------------------------


@pytest.mark.parametrize("hidden", ["[0]", "[-5]"])
def test_layer_widths_are_validated(hidden):
    with pytest.raises(
        ValueError, match=re.escape(f"algo.hidden = {hidden} must be zero or more positive layer")
    ):
        make_config(f"algo.hidden={hidden}")


@pytest.mark.parametrize("rollouts", [10_000_000, 1_000_000_000])
def test_a_config_that_cannot_fit_in_memory_is_refused_before_compiling(rollouts):
    with pytest.raises(ValueError, match=r"training needs about .* GB .*lower algo.rollouts"):
        make_config(f"algo.rollouts={rollouts}")


def test_an_unwritable_run_directory_is_named_with_the_fix(tmp_path):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    config = OmegaConf.create({"hydra": {"run": {"dir": str(blocker / "run")}}})
    with pytest.raises(SystemExit, match=rf"hydra.run.dir = {blocker / 'run'} cannot be written"):
        StartChecks().on_run_start(config)


def test_a_sweep_with_failed_jobs_exits_non_zero_naming_them(tmp_path):
    """Jobs that fail once launched (here: each job's directory finished with another
    configuration; invalid values refuse the whole sweep before any job, tests/test_cli.py)."""
    for job in ("0", "1"):
        with rundir.claim(tmp_path / job, composed(*S, "real.friction_gap=5")):
            (tmp_path / job / "summary.json").write_text('{"rows": []}')
    proc = hds_run_cli("-m", *S, "real.friction_gap=1,2", f"hydra.sweep.dir={tmp_path}")
    assert proc.returncode == 1
    assert "2 of 2 jobs failed: 0, 1" in proc.stderr
    assert all((tmp_path / job / "failed.txt").is_file() for job in ("0", "1"))


def test_a_launcher_timeout_of_zero_is_refused_before_the_sweep(tmp_path):
    config = OmegaConf.create(
        {"hydra": {"sweep": {"dir": str(tmp_path)}, "launcher": {"timeout_min": 0}}}
    )
    with pytest.raises(SystemExit, match="hydra.launcher.timeout_min = 0 gives every job no time"):
        StartChecks().on_multirun_start(config)


def test_a_checkpoint_written_before_progress_had_one_structure_restores(tmp_path):
    """Checkpoints written before TrainState.progress had one structure for every
    configuration hold only the progress arrays their configuration used (none, or keep-best's
    two): they restore into today's state, the arrays they lack at the state's own values."""
    from hds.algo.continuation import Continuation
    from hds.algo.pods import TrainState

    policy = {"w": jnp.arange(3.0)}
    progress = Continuation(epochs=6).init(policy)
    state = TrainState(policy, (jnp.zeros(2),), jnp.array(4), jax.random.PRNGKey(1), progress)
    plain = {"policy": policy, "opt_state": state.opt_state, "epoch": state.epoch}
    plain |= {"key": state.key}
    kept = plain | {"progress": {"best": {"w": jnp.arange(3.0) + 1}, "best_return": 2.0}}
    ckpt = Checkpoints(tmp_path / "ckpt")
    ckpt.save(4, plain, {"history": {}})
    ckpt.save(5, kept, {"history": {}})
    restored, meta = ckpt.restore(state, epoch=4)
    restored_kept, _ = ckpt.restore(state, epoch=5)
    ckpt.close()
    assert isinstance(restored, TrainState) and meta == {"history": {}}
    for a, b in zip(jax.tree.leaves(restored), jax.tree.leaves(state), strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(restored_kept.progress.best["w"], [1.0, 2.0, 3.0])
    assert float(restored_kept.progress.best_return) == 2.0
    assert int(restored_kept.progress.solved) == 6  # the state's own: not yet solved
