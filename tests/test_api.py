"""hds as a library: the Python API of the README, policies loaded, evaluated and exported, the
command-line tools over a finished run, and a two-step-size sweep labelled right everywhere."""

from __future__ import annotations

import ast
import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import mujoco
import numpy as np
import pytest

import hds
from hds.experiment import Hooks
from hds.utils.cli import run as cli_run
from tests.conftest import ROOT, command_main, wandb_keys, wandb_records

# Two step sizes x two seeds: four runs in one program.
SWEEP = (
    *("debug=fast", "algo.epochs=3", "algo.chunk=3", "seeds=2", "sweep.step_size=[0.01,0.04]"),
    "gif=true",
)
ENV = {**os.environ, "WANDB_MODE": "offline"}


def cli(*args, cwd=ROOT):
    proc = subprocess.run(
        [sys.executable, "-m", *args], cwd=cwd, env=ENV, capture_output=True, text=True
    )
    return proc


# The key=value commands over a finished run (hds.evaluate, hds.export, hds.report) run in this
# process: their main through hds.utils.cli.run, as their `__main__` calls it. A process of their
# own would only add its start-up (jax, brax: some seconds each): test_cli runs the installed
# hds-export's entry in a process of its own (and test_optuna `python -m hds.report`, slow).
def command(name: str, *args: str):
    """What `python -m hds.<name> args` returns (it prints `wrote <that>`)."""
    return cli_run(command_main(f"hds.{name}"), list(args))


def refused(capsys, name: str, *args: str) -> str:
    """The one line on stderr with which `python -m hds.<name> args` exits with status 1."""
    with pytest.raises(SystemExit) as ended:
        command(name, *args)
    err = capsys.readouterr().err
    assert ended.value.code == 1 and "Traceback" not in err
    (line,) = err.strip().splitlines()
    return line


@pytest.fixture(scope="module")
def sweep_run(tmp_path_factory):
    """`python -m hds.run` on the sweep, with W&B offline; its directory and console."""
    out = tmp_path_factory.mktemp("sweep") / "run"
    proc = cli("hds.run", *SWEEP, f"hydra.run.dir={out}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, proc.stdout


def test_a_sweep_of_two_step_sizes_is_labelled_everywhere(sweep_run, tmp_path):
    out, console = sweep_run
    # console: every swept value printed as it is (not 0.0 for both)
    assert "0.01" in console and "0.04" in console
    # summary.json: one row per run, each with its seed and step size
    rows = json.loads((out / "summary.json").read_text())["rows"]
    assert sorted((r["seed"], r["step_size"]) for r in rows) == [
        (0, 0.01), (0, 0.04), (1, 0.01), (1, 0.04)
    ]  # fmt: skip
    # report.md and report.csv: a row per setting (not averaged as seeds), a step_size column
    command("report", f"dir={out}", f"out={tmp_path}")
    report = (tmp_path / "report.md").read_text()
    assert "| pods step_size=0.01 | coulomb_friction@slider | 2 |" in report
    assert "| pods step_size=0.04 | coulomb_friction@slider | 2 |" in report
    with open(tmp_path / "report.csv") as f:
        table = list(csv.DictReader(f))
    assert {(r["seed"], r["step_size"]) for r in table} == {
        ("0", "0.01"), ("0", "0.04"), ("1", "0.01"), ("1", "0.04")
    }  # fmt: skip
    # W&B: per-run keys named by seed and setting, epoch as the step, final returns as summary
    (records,) = wandb_records(out).values()
    keys = wandb_keys(records, "history")
    for label in ("seed0_step_size0.01", "seed1_step_size0.01", "seed1_step_size0.04"):
        assert f"return/{label}" in keys
    assert "epoch" in keys
    # the GIF of the first run, drawn beside the plant, as a file and as a W&B video
    assert (out / "plots" / "pods_sim_vs_real.gif").read_bytes()[:6] == b"GIF89a"
    assert json.loads(keys["sim_vs_real_gif/_type"]) == "video-file"
    assert json.loads(keys["sim_vs_real_gif/path"]).endswith(".gif")
    summary = wandb_keys(records, "summary")
    assert {"real_return/mean", "gap/seed1_step_size0.04", "sim_return/seed0_step_size0.01"} <= (
        set(summary)
    )


def test_a_saved_policy_loads_and_gives_the_run_s_numbers(sweep_run):
    out, _ = sweep_run
    rows = json.loads((out / "summary.json").read_text())["rows"]
    row = next(r for r in rows if (r["seed"], r["step_size"]) == (1, 0.04))
    policy = hds.load_policy(out, seed=1, step_size=0.04)
    assert policy.method == "pods" and policy.run == {"seed": 1, "step_size": 0.04}
    assert policy.epoch == 3
    # its return on the run's plant, from the run's evaluation states, is the row's
    assert hds.evaluate_policy(policy).mean_ci()[0] == pytest.approx(row["real_return"], rel=1e-5)
    # numpy in, numpy out; jax in, jax out (differentiable)
    obs = np.zeros((3, len(policy.obs_names)), np.float32)
    u = policy(obs)
    assert isinstance(u, np.ndarray) and u.shape == (3, 1)
    grad = jax.grad(lambda o: policy(o).sum())(jax.numpy.asarray(obs[0]))
    assert np.all(np.isfinite(grad)) and np.any(grad != 0)
    # ambiguous or unknown runs are named
    with pytest.raises(ValueError, match="seed0_step_size0.01"):
        hds.load_policy(out, seed=1)
    with pytest.raises(FileNotFoundError, match="no checkpoint of method 'hds"):
        hds.load_policy(out, method="hds+mlp")


def test_a_policy_loads_from_its_saved_artefact_and_from_an_older_run_s_checkpoint(
    sweep_run, tmp_path
):
    """The run saves each method's policies (network spec + parameters, policies/<method>):
    loading one builds no trainer. A run directory written before that artefact existed (only
    config.yaml and checkpoints/) loads the same policy from its last checkpoint."""
    import shutil

    from hds.policy_store import FORMAT

    out, _ = sweep_run
    spec = json.loads((out / "policies" / "pods" / "policy.json").read_text())
    assert spec["format"] == FORMAT and spec["epochs"] == [3, 3, 3, 3]
    assert [r["step_size"] for r in spec["runs"]] == [0.01, 0.01, 0.04, 0.04]
    older = tmp_path / "older"
    shutil.copytree(out / "checkpoints", older / "checkpoints")
    shutil.copy(out / "config.yaml", older / "config.yaml")
    for seed, step_size in ((0, 0.01), (1, 0.04)):
        saved = hds.load_policy(out, seed=seed, step_size=step_size)
        restored = hds.load_policy(older, seed=seed, step_size=step_size)
        assert restored.epoch == saved.epoch == 3
        for a, b in zip(jax.tree.leaves(saved.params), jax.tree.leaves(restored.params)):
            np.testing.assert_array_equal(a, b)
        obs = np.random.default_rng(seed).normal(size=(5, len(saved.obs_names)))
        np.testing.assert_array_equal(saved(obs), restored(obs))


def test_a_policy_runs_on_a_raw_mujoco_data_as_the_readme_says(sweep_run):
    out, _ = sweep_run
    policy = hds.load_policy(out, seed=0, step_size=0.01)
    model = policy.mj_model()
    data = mujoco.MjData(model)
    data.qpos[:] = [0.1, 0.05]
    for _ in range(25):
        data.ctrl[:] = policy(policy.observe(data))
        mujoco.mj_step(model, data, policy.frames)
    assert np.all(np.isfinite(data.qpos)) and data.time == pytest.approx(25 * policy.dt)


def test_the_exported_policy_gives_the_in_process_return_on_c_mujoco(sweep_run, tmp_path):
    out, _ = sweep_run
    written = command("export", f"run={out}", "seed=1", "step_size=0.01", f"out={tmp_path}")
    assert written == tmp_path
    contract = json.loads((tmp_path / "policy.json").read_text())
    assert contract["observations"] == ["q_slider", "q_hinge", "qd_slider", "qd_hinge"]
    assert contract["actions"] == ["slide"] and contract["control_range"] == [[-3.0, 3.0]]
    assert contract["dt"] == pytest.approx(0.04) and (tmp_path / contract["mjcf"]).is_file()
    # numpy_policy.py runs with numpy alone: import it in a process that has no jax
    code = (
        "import sys, json, numpy as np; sys.modules['jax'] = None; sys.path.insert(0, sys.argv[1]);"
        "import numpy_policy; p = numpy_policy.load(sys.argv[1]);"
        "print(json.dumps(p(np.ones((2, 4), np.float32)).tolist()))"
    )
    numpy_out = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True
    )
    assert numpy_out.returncode == 0, numpy_out.stderr
    policy = hds.load_policy(out, seed=1, step_size=0.01)
    np.testing.assert_allclose(
        json.loads(numpy_out.stdout), policy(np.ones((2, 4), np.float32)), atol=1e-6
    )
    # the same return on the C MuJoCo plant
    sys.path.insert(0, str(tmp_path))
    try:
        import numpy_policy

        exported = numpy_policy.load(tmp_path)
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("numpy_policy", None)
    in_process = hds.evaluate_policy(policy, episodes=8)
    from hds.data import initial_states
    from hds.real import make_plant, rollout

    plant = make_plant(policy.config.real, policy.env)
    q0, qd0 = initial_states(policy.simulator.task, policy.config.eval_seed, 8)
    task = policy.simulator.task
    returns = rollout(plant, task, q0, qd0, exported, task.horizon).returns
    np.testing.assert_allclose(returns, in_process.returns, rtol=1e-4)


def test_hds_export_into_a_place_it_cannot_write_is_one_line(sweep_run, tmp_path, capsys):
    """out= below a file (a read-only directory reads the same, but root writes into those)."""
    out, _ = sweep_run
    (tmp_path / "a_file").write_text("")
    args = [f"run={out}", "seed=1", "step_size=0.01", f"out={tmp_path / 'a_file' / 'policy'}"]
    line = refused(capsys, "export", *args)
    assert str(tmp_path / "a_file") in line and "fix the path" in line, line


def test_format_onnx_runs_in_onnxruntime_as_the_policy_does_on_c_mujoco(
    sweep_run, tmp_path, capsys
):
    """hds.export format=onnx: policy.onnx in onnxruntime gives the in-process policy's
    controls (to 1e-5) and its return on the C MuJoCo plant; the JSON contract beside it."""
    import onnx
    import onnxruntime

    out, _ = sweep_run
    args = (f"run={out}", "seed=1", "step_size=0.01", f"out={tmp_path}")
    assert command("export", *args, "format=onnx") == tmp_path
    contract = json.loads((tmp_path / "policy.json").read_text())
    assert contract["onnx"] == {
        "file": "policy.onnx",
        "input": "obs",
        "output": "action",
        "opset": 17,
    }
    assert (tmp_path / "policy.npz").is_file() and (tmp_path / contract["mjcf"]).is_file()
    model = onnx.load(tmp_path / "policy.onnx")
    meta = {p.key: p.value for p in model.metadata_props}
    assert meta["observations"] == "q_slider,q_hinge,qd_slider,qd_hinge"
    assert json.loads(meta["trained_on"])["simulator"] == "nominal"
    session = onnxruntime.InferenceSession(
        str(tmp_path / "policy.onnx"), providers=["CPUExecutionProvider"]
    )
    policy = hds.load_policy(out, seed=1, step_size=0.01)
    # fixed observations, angles past +-pi too (the hinge enters as sin, cos)
    obs = (np.random.default_rng(0).normal(size=(256, 4)) * [0.5, 4.0, 2.0, 6.0]).astype(np.float32)
    (controls,) = session.run(["action"], {"obs": obs})
    np.testing.assert_allclose(controls, policy(obs), rtol=0, atol=1e-5)
    assert np.ptp(controls) > 1e-3  # the check above compared controls that vary
    from hds.data import initial_states
    from hds.real import make_plant, rollout

    in_process = hds.evaluate_policy(policy, episodes=8)
    task = policy.simulator.task
    q0, qd0 = initial_states(task, policy.config.eval_seed, 8)
    plant = make_plant(policy.config.real, policy.env)
    act = lambda o: session.run(None, {"obs": np.asarray(o, np.float32)})[0]  # noqa: E731
    returns = rollout(plant, task, q0, qd0, act, task.horizon).returns
    np.testing.assert_allclose(returns, in_process.returns, rtol=1e-5)
    # an unknown format is one line, before any checkpoint is read
    line = refused(capsys, "export", *args, "format=tflite")
    assert "format='tflite' is not an export format; choose json" in line, line


def test_the_api_lists_its_names_and_a_policy_prints_short(sweep_run):
    out, _ = sweep_run
    assert {"load_policy", "train", "evaluate_policy", "export_policy", "compose"} <= set(dir(hds))
    policy = hds.load_policy(out, seed=1, step_size=0.04)
    text = repr(policy)
    assert len(text) < 300 and "Array" not in text and "kernel" not in text, text
    assert "method='pods'" in text and "'step_size': 0.04" in text and "hidden=" in text
    ci = hds.evaluate_policy(policy, episodes=4).mean_ci()
    assert ci.low <= ci.mean <= ci.high and tuple(ci) == (ci.mean, ci.low, ci.high)


def test_hds_evaluate_runs_a_saved_policy_on_another_plant(sweep_run, tmp_path, capsys):
    out, _ = sweep_run
    args = (f"run={out}", "seed=0", "step_size=0.04", "eval_episodes=4", f"out={tmp_path}")
    capsys.readouterr()
    assert command("evaluate", *args, "real=brax", "real.friction_gap=3") == tmp_path
    console = capsys.readouterr().out
    result = json.loads((tmp_path / "evaluation.json").read_text())
    assert result["real"]["plant"] == {
        "plant": "brax",
        "friction_gap": 3.0,
        "effects": result["real"]["plant"]["effects"],
    }
    # the force the plant applied: 3 x the configured 20 N
    (friction,) = result["real"]["plant"]["effects"]
    assert friction["params"] == {"force": 60.0}
    assert len(result["real"]["returns"]) == len(result["sim"]["returns"]) == 4
    assert result["gap"] == pytest.approx(result["sim"]["mean"] - result["real"]["mean"])
    lo, hi = result["gap_ci95"]
    assert lo <= result["gap"] <= hi
    # the console says what came out: returns, gap and their intervals
    real, sim = result["real"], result["sim"]
    for line in (
        f"return on the brax plant (coulomb_friction@slider {{force: 60}}): {real['mean']:.4g} "
        f"[{real['ci95'][0]:.4g}, {real['ci95'][1]:.4g}]",
        f"return on the simulator it trained on: {sim['mean']:.4g} [{sim['ci95'][0]:.4g}, ",
        f"sim2real gap (simulator - plant): {result['gap']:.4g} [{lo:.4g}, {hi:.4g}]",
    ):
        assert line in console, console
    assert (tmp_path / "plots" / "trajectories.png").is_file()
    assert (tmp_path / "sim_vs_real.gif").stat().st_size > 0
    # more friction, a worse return than on the run's own plant
    own = hds.evaluate_policy(hds.load_policy(out, seed=0, step_size=0.04), episodes=4)
    assert result["real"]["mean"] < own.mean_ci()[0]
    # what the user can fix is one line
    line = refused(capsys, "evaluate", f"run={out}", "seed=7", "step_size=0.04")
    assert "none of this run's runs match seed=7" in line, line


def test_hds_evaluate_runs_a_policy_through_a_learned_model(sweep_run, tmp_path):
    """model=: through a model that is the simulator the policy trained on, it scores its
    simulator return from the same initial states; the model's errors along its episodes."""
    from hds import dynamics

    main = command_main("hds.evaluate")
    out, _ = sweep_run
    policy = hds.load_policy(out, seed=0, step_size=0.04)
    exact = dynamics.save(tmp_path / "model", dynamics.zero_residual(policy.simulator))
    args = [f"run={out}", "seed=0", "step_size=0.04", "eval_episodes=4", "gif=false"]
    written = main([*args, f"model={exact}", f"out={tmp_path / 'eval'}"])
    result = json.loads((written / "evaluation.json").read_text())
    np.testing.assert_allclose(result["model"]["returns"], result["sim"]["returns"], rtol=1e-4)
    assert result["model"]["k_step"]["1"]["model"] == pytest.approx(
        result["model"]["k_step"]["1"]["simulator"]
    )
    with pytest.raises(FileNotFoundError):
        main([*args, f"model={tmp_path / 'none'}", f"out={tmp_path / 'eval2'}"])


def test_train_calls_its_hooks_and_returns_a_typed_result(tmp_path):
    epochs, params_seen = [], []
    hooks = Hooks(
        progress_fn=lambda epoch, metrics: epochs.append((epoch, metrics)),
        policy_params_fn=lambda epoch, params: params_seen.append((epoch, params)),
        console=False,
    )
    cfg = hds.compose(["debug=fast", "logger=none", "seeds=2", "real=none"])
    result = hds.train(cfg, out_dir=tmp_path, hooks=hooks)
    assert [e for e, _ in epochs] == list(range(1, cfg.algo.epochs + 1))
    assert {m["method"] for _, m in epochs} == {"pods"}
    assert all(m["return"].shape == (2,) for _, m in epochs)
    history = np.asarray(result.histories["pods"]["return"])
    np.testing.assert_allclose(history[:, -1], epochs[-1][1]["return"])
    assert [e for e, _ in params_seen] == [3, 6]
    assert jax.tree.leaves(params_seen[-1][1])[0].shape[0] == 2
    assert [(r["method"], r["seed"]) for r in result.rows] == [("pods", 0), ("pods", 1)]
    assert json.loads((tmp_path / "summary.json").read_text()) == json.loads(
        json.dumps(result.summary())
    )


def test_jobs_side_by_side_print_a_line_each_tenth_not_a_live_bar(tmp_path, capsys):
    from omegaconf import OmegaConf

    from hds.logger import RunLogger
    from hds.run import one_job_at_a_time

    cfg = hds.compose(["debug=fast", "logger=none"])
    logger = RunLogger(cfg, tmp_path, "pods_cl", cfg.runs(), live=False)
    logger.start(first_epoch=0)
    for _ in range(2):
        logger.log_epochs(0, {"return": np.full((1, 3), -12.34)}, 0.1)
    logger.close()
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(" (")[0] for line in lines] == [
        "pods_cl epoch 3/6 return -12.3",
        "pods_cl epoch 6/6 return -12.3",
    ]
    cfg = hds.compose(["debug=fast", "logger=none", "algo.epochs=100"])
    logger = RunLogger(cfg, tmp_path, "hds", cfg.runs(), live=False)
    logger.start(first_epoch=0)
    for chunk in [3] * 33 + [1]:  # a line where a tenth is crossed, and at the end
        logger.log_epochs(0, {"return": np.full((1, chunk), -1.0)}, 0.1)
    logger.close()
    epochs = [int(line.split()[2].split("/")[0]) for line in capsys.readouterr().out.splitlines()]
    assert epochs == [12, 21, 30, 42, 51, 60, 72, 81, 90, 100]

    def hydra(mode, launcher):
        return OmegaConf.create({"mode": mode, "launcher": {"_target_": launcher}})

    basic, joblib = (
        "hydra._internal.core_plugins.basic_launcher.BasicLauncher",
        "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher",
    )
    from hydra.types import RunMode

    assert one_job_at_a_time(hydra(RunMode.RUN, joblib))
    assert one_job_at_a_time(hydra(RunMode.MULTIRUN, basic))
    assert not one_job_at_a_time(hydra(RunMode.MULTIRUN, joblib))


# after the first chunk; after the last one (make test-slow: the same path, later)
@pytest.mark.parametrize("killed_at", [3, pytest.param(6, marks=pytest.mark.slow)])
def test_a_failing_run_closes_its_w_and_b_run_and_a_resume_continues_it(tmp_path, killed_at):
    cfg = hds.compose(["debug=fast", "real=none", "logger.group=test"])

    def die(epoch, params):
        if epoch == killed_at:
            raise KeyboardInterrupt(f"killed after the checkpoint of epoch {epoch}")

    with pytest.raises(KeyboardInterrupt):
        hds.train(cfg, tmp_path, Hooks(policy_params_fn=die, console=False))
    (first,) = wandb_records(tmp_path).values()
    assert [r.exit.exit_code for r in first if r.HasField("exit")] == [1]
    assert not (tmp_path / "summary.json").exists()
    hds.train(cfg, tmp_path, Hooks(console=False))
    runs = wandb_records(tmp_path)
    assert len(runs) == 2 and len({name.rsplit("-", 1)[1] for name in runs}) == 1  # one run id
    second = runs[max(runs)]
    assert "real_return/mean" in wandb_keys(second, "summary")
    epochs = [
        json.loads(i.value_json)
        for r in second
        if r.HasField("history")
        for i in r.history.item
        if (i.key or "/".join(i.nested_key)) == "epoch"
    ]
    # the resumed run logs the epochs after the checkpoint, and its summary in any case
    assert sorted(set(epochs) - {0}) == list(range(killed_at + 1, 7))  # 0: W&B's default


# Each layer calls downward only: the jitted core never imports the experiment layer, the
# experiment layer never the tools built on it.
TOOLS = {"run", "evaluate", "export", "report", "callbacks", "policy"}
LAYERS = {
    "core": ("algo", "envs", "effects", "real", "data", "dynamics", "networks", "noise"),
    "experiment": ("experiment",),
}


def _imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("hds."):
            names.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            names |= {a.name.split(".")[1] for a in node.names if a.name.startswith("hds.")}
    return names


def test_no_module_imports_upward():
    package = ROOT / "hds"
    for path in package.rglob("*.py"):
        top = path.relative_to(package).parts[0].removesuffix(".py")
        above = TOOLS | {"experiment"} if top in LAYERS["core"] else set()
        if top == "experiment":
            above = TOOLS
        wrong = _imports(path) & above
        assert not wrong, f"{path.relative_to(ROOT)} imports {wrong}, a layer above it"


def test_an_older_run_s_checkpoint_gives_the_kept_best_policy_where_one_was_found(tmp_path):
    """algo.keep=best: a checkpoint holds the last iterate and the best one (progress.best);
    read as stored, each run returns its best where it found one (best_return > -inf), else
    its last iterate, as the trainer's final_policy does."""
    import jax.numpy as jnp

    from hds.algo.pods import TrainState
    from hds.checkpoint import Checkpoints
    from hds.policy_store import from_checkpoint

    last = {"params": {"Dense_0": {"kernel": jnp.ones((2, 3, 4)), "bias": jnp.ones((2, 4))}}}
    best = jax.tree.map(lambda x: 2 * x, last)
    progress = {"best": best, "best_return": jnp.asarray([-5.0, -jnp.inf])}
    state = TrainState(last, (), jnp.asarray([7, 7]), jnp.zeros((2, 2), jnp.uint32), progress)
    ckpt = Checkpoints(tmp_path / "pods")
    ckpt.save(7, state, {"history": {}, "method": "pods"})
    ckpt.close()
    params, epochs = from_checkpoint(tmp_path / "pods")
    assert list(epochs) == [7, 7]
    kernel = params["params"]["Dense_0"]["kernel"]
    assert np.all(kernel[0] == 2.0) and np.all(kernel[1] == 1.0)
