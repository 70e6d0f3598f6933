"""Sweeps: vmapped inside one program or as Hydra multiruns (basic, joblib, submitit_local), the
two agreeing; sharding across host devices; a failed job that a restarted sweep reruns while it
skips the finished ones; a killed sweep that resumes; one W&B group per sweep; and hds.report on
the result."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from hds import experiment
from hds import run as hds_run
from hds.envs import make_env
from tests.conftest import FAST, ROOT, TINY, make_config, trained, wandb_records


def cli(*args) -> list[str]:
    return [sys.executable, "-m", "hds.run", *args]


def cli_env(env_vars=None) -> dict:
    return {**os.environ, "WANDB_MODE": "offline", **(env_vars or {})}


def hds_run_cli(*args, env_vars=None, timeout=900, cwd=ROOT, returncode=0):
    proc = subprocess.run(
        cli(*args), cwd=cwd, env=cli_env(env_vars), capture_output=True, text=True, timeout=timeout
    )
    assert proc.returncode == returncode, proc.stdout[-2000:] + proc.stderr[-3000:]
    return proc


def assert_every_job_finished(sweep: Path, jobs: set[str]) -> dict:
    """The sweep's own summary.json gathers the rows of every job, and none failed."""
    summary = json.loads((sweep / "summary.json").read_text())
    assert {r["job"] for r in summary["rows"]} == jobs and summary["failed_jobs"] == []
    return summary


def wandb_groups(run_dir: Path) -> list[str]:
    """The W&B group of every offline run below run_dir, read back from its run record."""
    return [
        next(r.run.run_group for r in records if r.HasField("run"))
        for records in wandb_records(run_dir).values()
    ]


@pytest.mark.parametrize(
    "swept, setting, metric, base",
    [
        ("step_size", "algo.step_size", "step_size", ()),
        pytest.param(
            "noise_decay",
            "noise.decay",
            "noise",
            ("noise=exponential", "noise.scale=0.3"),
            marks=pytest.mark.slow,  # make test-slow: step_size covers the vmapped path
        ),
    ],
)
def test_a_vmapped_sweep_gives_the_numbers_of_separate_runs(tmp_path, swept, setting, metric, base):
    values = (0.1, 0.5) if swept == "noise_decay" else (0.01, 0.04)
    cfg = make_config(*TINY, *base, f"sweep.{swept}=[{values[0]},{values[1]}]")
    env = make_env(cfg.env)
    together, history = trained(cfg, env, tmp_path / "vmapped", "pods")
    for i, value in enumerate(values):
        alone, alone_history = trained(
            make_config(*TINY, *base, f"{setting}={value}"), env, tmp_path / f"alone{i}", "pods"
        )
        for a, b in zip(jax.tree.leaves(together), jax.tree.leaves(alone)):
            np.testing.assert_allclose(a[i], b[0], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(history["return"][i], alone_history["return"][0], rtol=1e-5)
    assert not np.allclose(history[metric][0], history[metric][1])


# a swept value's numbers equal a separate run's, in make test: the step-size sweep above
@pytest.mark.slow
def test_a_vmapped_friction_gap_sweep_gives_the_numbers_of_separate_runs(tmp_path, capsys):
    """The oracle trains on each gap's dynamics and every run meets its own plant, in one
    program; the same numbers as one run per gap."""
    base = (*TINY, "method=oracle", "env.task.horizon=20")
    together = experiment.run(make_config(*base, "sweep.friction_gap=[0,3]"), tmp_path / "vmapped")
    assert "friction_gap" in capsys.readouterr().out  # the console table tells the runs apart
    rows = {r["friction_gap"]: r for r in together.rows}
    for gap in (0.0, 3.0):
        (alone,) = experiment.run(
            make_config(*base, f"real.friction_gap={gap}"), tmp_path / f"{gap}"
        ).rows
        for key in ("sim_return", "real_return"):
            assert rows[gap][key] == pytest.approx(alone[key], rel=1e-5), (gap, key)
    assert abs(rows[3.0]["real_return"] - rows[0.0]["real_return"]) > 1.0  # the gap matters


def test_a_seeds_numbers_do_not_depend_on_the_seeds_beside_it(tmp_path):
    """On one CPU the runs of a batch loop inside their program (vmap_runs auto): seed 1 of
    `seeds=2` is bit for bit seed 1 alone. Vmapping them (vmap_runs=0) agrees to float level."""
    cfg = make_config(*TINY, "seeds=2")
    env = make_env(cfg.env)
    looped, history = trained(cfg, env, tmp_path / "looped", "pods")
    alone, alone_history = trained(make_config(*TINY, "seed=1"), env, tmp_path / "alone", "pods")
    for a, b in zip(jax.tree.leaves(looped), jax.tree.leaves(alone)):
        np.testing.assert_array_equal(a[1], b[0])
    assert history["return"][1] == alone_history["return"][0]
    vmapped, _ = trained(
        make_config(*TINY, "seeds=2", "vmap_runs=0"), env, tmp_path / "vmapped", "pods"
    )
    for a, b in zip(jax.tree.leaves(looped), jax.tree.leaves(vmapped)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("setting, vmapped", [(None, 1), (0, 5), (2, 2), (9, 5)])
def test_runs_map_as_vmap_runs_says(setting, vmapped):
    """vmap_runs on one CPU: auto loops, 0 vmaps all, K vmaps groups of K (5 runs: two groups
    and a remainder); every way gives each run what it gives alone."""
    from hds.utils.runtime import over_runs, runs_vmapped

    assert runs_vmapped(setting, 5) == vmapped

    def fn(x, scale):  # a branch, as early stopping has
        return jax.lax.cond(x.sum() > 0, lambda: x * scale, lambda: -x), x.sum()

    x = jax.random.normal(jax.random.PRNGKey(0), (5, 3))
    scale = jax.numpy.arange(5.0)
    out = jax.jit(over_runs(fn, vmapped, 5))(x, scale)
    for i in range(5):
        alone = fn(x[i], scale[i])
        np.testing.assert_allclose(out[0][i], alone[0], rtol=1e-6)
        np.testing.assert_allclose(out[1][i], alone[1], rtol=1e-6)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_run_by_run_compiles_one_runs_program_for_every_batch(threads):
    """A single CPU trains a batch run by run through one program of one run's shapes
    (RunByRun), the runs shared out to `threads` threads: each run's numbers bit for bit the
    lax.map loop's, in the batch's order, and a batch of any size reuses the one compile."""
    from hds.utils.runtime import RunByRun, over_runs

    def fn(x, scale):  # a branch, as early stopping has
        return jax.lax.cond(x.sum() > 0, lambda: x * scale, lambda: -x), x.sum()

    x = jax.random.normal(jax.random.PRNGKey(0), (5, 3))
    scale = jax.numpy.arange(5.0)
    looped = jax.jit(over_runs(fn, 1, 5))(x, scale)
    program = RunByRun(fn, threads=threads).lower(x, scale).compile()
    assert program.threads == threads
    for out in (program(x, scale), RunByRun(fn, threads=threads)(x, scale)):
        for a, b in zip(out, looped):
            assert a.shape == b.shape
            np.testing.assert_array_equal(a, b)
    three = program(x[:3], scale[:3])  # another batch size: the same compiled program
    np.testing.assert_array_equal(three[0], looped[0][:3])


@pytest.mark.slow  # make test-slow: keeps make test under 10 min cold
def test_the_batch_is_sharded_across_two_host_devices(tmp_path):
    code = (
        "import jax, json, sys; from tests.conftest import make_config, trained;"
        "from hds.envs import make_env;"
        f"cfg = make_config(*{list(TINY)!r}, 'seeds=2');"
        "out = __import__('pathlib').Path(sys.argv[1]);"
        "p, h = trained(cfg, make_env(cfg.env), out, 'pods');"
        "leaf = jax.tree.leaves(p)[0];"
        "print(json.dumps({'devices': jax.device_count(), 'shards': len(leaf.sharding.device_set),"
        " 'return': h['return']}))"
    )
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    proc = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "sharded")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["devices"] == 2 and out["shards"] == 2
    cfg = make_config(*TINY, "seeds=2")
    _, history = trained(cfg, make_env(cfg.env), tmp_path / "single", "pods")
    np.testing.assert_allclose(out["return"], history["return"], rtol=1e-5)


@pytest.fixture(scope="module")
def restarted_sweep(tmp_path_factory):
    """A basic-launcher sweep whose second job fails once launched (its directory holds a run
    finished with another configuration; an invalid value would refuse the whole sweep before
    any job), then the same sweep started again once that directory is cleared."""
    from hydra import compose, initialize_config_dir

    from hds import rundir

    tmp = tmp_path_factory.mktemp("sweep")
    sweep = tmp / "sweep"
    with initialize_config_dir(config_dir=str(ROOT / "hds" / "conf"), version_base="1.3"):
        other = compose("config", overrides=[*TINY, "seed=7"])
    with rundir.claim(sweep / "1", other):
        (sweep / "1" / "summary.json").write_text('{"rows": []}')
    args = ["-m", *TINY, "seed=0,1", f"hydra.sweep.dir={sweep}"]
    first = hds_run_cli(*args, returncode=1)  # a sweep with a failed job exits non-zero
    state = {
        "first_failed": (sweep / "1" / "failed.txt").is_file(),
        "first_summary": json.loads((sweep / "summary.json").read_text()),
        "job0_mtime": (sweep / "0" / "summary.json").stat().st_mtime_ns,
        "first_stdout": first.stdout,
    }
    shutil.rmtree(sweep / "1")
    second = hds_run_cli(*args)
    return sweep, state, second


def test_a_failed_job_keeps_the_others_results(restarted_sweep):
    _, state, _ = restarted_sweep
    assert state["first_failed"]
    assert state["first_summary"]["failed_jobs"] == ["1"]
    assert {r["job"] for r in state["first_summary"]["rows"]} == {"0"}


def test_a_restarted_sweep_skips_finished_jobs_and_reruns_failed_ones(restarted_sweep):
    sweep, state, second = restarted_sweep
    assert (sweep / "0" / "summary.json").stat().st_mtime_ns == state["job0_mtime"]
    assert not (sweep / "1" / "failed.txt").exists()
    assert_every_job_finished(sweep, {"0", "1"})


def test_a_sweep_ends_with_a_few_lines_per_method_and_a_figure(restarted_sweep):
    """Not a row per seed: per method, its mean real return and gap with their intervals and
    the seeds that solve the task (hds.story), and the figure beside summary.json."""
    sweep, state, second = restarted_sweep
    story = second.stdout[second.stdout.index(f"2 jobs in {sweep}") :]
    lines = story.splitlines()
    assert lines[2].startswith("On the plant coulomb_friction@slider: best pods, real return ")
    assert lines[3] == "pods (2 seeds)"  # both jobs' seed 0: one method on one plant
    assert lines[4].startswith("  real return ") and "   sim2real gap " in lines[4]
    assert lines[5].startswith("  solved by ") and lines[5].endswith("/2 on the plant")
    assert f"figure: {sweep / 'plots' / 'summary.png'}" in story
    assert (sweep / "plots" / "summary.png").is_file()
    assert "1 jobs in" not in state["first_stdout"] and "1 job in" in state["first_stdout"]


@pytest.fixture(scope="module")
def killed_sweep(tmp_path_factory):
    """A sweep over two methods (so two config names) in the default sweep directory, with W&B
    offline, killed (SIGKILL) as soon as its first job has finished, then started again on that
    directory (`hydra.sweep.dir=`), as `hds_run_cli` starts any sweep."""
    tmp = tmp_path_factory.mktemp("killed")
    # conftest.FAST, not TINY: both methods' chunks are then programs other files compile
    # (test_train's PODS and its closed-loop improvement), read from the shared cache
    fast_wandb = [a for a in FAST if a != "logger=none"]  # conf/config.yaml: logger=wandb
    args = ["-m", *fast_wandb, "real=none", "method=pods,pods_cl"]
    first = subprocess.Popen(
        cli(*args),
        cwd=tmp,  # outputs/multiruns/<name>/<time>/ lands in tmp
        env=cli_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # its own process group: the kill takes its children too
    )
    try:
        deadline = time.monotonic() + 600
        while not (done := list(tmp.glob("outputs/multiruns/*/*/0/summary.json"))):
            assert first.poll() is None, "the sweep ended before its first job had finished"
            assert time.monotonic() < deadline, "the first job did not finish in 600 s"
            time.sleep(0.2)
    finally:
        os.killpg(first.pid, signal.SIGKILL)
        first.wait()
    sweep = done[0].parents[1]
    state = {
        "finished_at_kill": sorted(p.parent.name for p in sweep.glob("*/summary.json")),
        "job0_summary": (sweep / "0" / "summary.json").read_bytes(),
        "job0_mtime": (sweep / "0" / "summary.json").stat().st_mtime_ns,
    }
    second = hds_run_cli(*args, f"hydra.sweep.dir={sweep}", cwd=tmp)
    return tmp, sweep, state, second


def test_a_killed_sweep_resumes_without_retraining_finished_jobs(killed_sweep):
    tmp, sweep, state, second = killed_sweep
    assert state["finished_at_kill"] == ["0"]  # killed while job 1 was unfinished
    assert (sweep / "0" / "summary.json").read_bytes() == state["job0_summary"]
    assert (sweep / "0" / "summary.json").stat().st_mtime_ns == state["job0_mtime"]
    assert f"{sweep / '0'} is finished (summary.json exists): skipped" in second.stdout
    summary = assert_every_job_finished(sweep, {"0", "1"})
    assert sorted(r["method"] for r in summary["rows"]) == ["pods", "pods_cl"]
    # both methods' jobs in the one sweep directory, though their names differ
    assert list(tmp.glob("outputs/multiruns/*/*")) == [sweep]


def test_the_jobs_of_a_sweep_share_one_wandb_group(killed_sweep):
    """Every job's W&B offline runs (job 1's from before the kill and after the restart) carry
    the sweep's group, `multiruns/<name>/<time>` of its directory: not the jobs' names, not another
    sweep's."""
    _, sweep, _, _ = killed_sweep
    group = f"multiruns/cartpole_balance-pods/{sweep.name}"
    assert sweep.parent.name == "cartpole_balance-pods"
    assert wandb_groups(sweep / "0") == [group]  # trained once: not retrained on restart
    job1 = wandb_groups(sweep / "1")
    assert job1 and set(job1) == {group}


def test_hds_report_on_a_sweep(restarted_sweep):
    from hds.report import build

    sweep, *_ = restarted_sweep
    report = build(sweep).read_text()
    assert "| pods | coulomb_friction@slider | 2 |" in report  # both jobs: same method and plant
    assert (sweep / "report.csv").read_text().count("\n") == 3  # header and one row per job
    assert (sweep / "plots" / "report_sim_vs_real.png").is_file()


def test_hds_report_elsewhere_with_an_animation(restarted_sweep, tmp_path):
    from hds.report import main

    sweep, *_ = restarted_sweep
    main([f"dir={sweep}", f"out={tmp_path}", "gif=1"])
    assert (tmp_path / "report.md").read_text().count("| pods |") == 1
    assert (tmp_path / "report.csv").is_file()
    gif = tmp_path / "plots" / "pods_sim_vs_real.gif"
    assert gif.read_bytes()[:6] == b"GIF89a"


def test_a_single_run_has_a_wandb_group_of_its_own():
    from types import SimpleNamespace

    from hydra.types import RunMode

    sweep = "outputs/multiruns/cartpole_balance-pods/2026-01-02_03-04-05"
    runs = [f"outputs/runs/cartpole_balance-pods/2026-01-02_03-04-0{i}" for i in (5, 6)]
    as_job = lambda mode, out: SimpleNamespace(  # noqa: E731
        mode=mode, sweep=SimpleNamespace(dir=sweep), runtime=SimpleNamespace(output_dir=out)
    )
    groups = [hds_run.wandb_group(as_job(RunMode.MULTIRUN, f"{sweep}/{j}")) for j in (0, 1)]
    assert groups == ["multiruns/cartpole_balance-pods/2026-01-02_03-04-05"] * 2
    singles = [hds_run.wandb_group(as_job(RunMode.RUN, run)) for run in runs]
    assert singles == [
        "runs/cartpole_balance-pods/2026-01-02_03-04-05",
        "runs/cartpole_balance-pods/2026-01-02_03-04-06",
    ]


def test_hds_report_names_what_it_expects_where_there_is_nothing(tmp_path):
    from hds.report import build

    with pytest.raises(FileNotFoundError) as err:
        build(tmp_path)
    for expected in ("summary.json", "python -m hds.run", "report.json", "python -m hds.discover"):
        assert expected in str(err.value)


@pytest.fixture(scope="module")
def vmapped_seeds(tmp_path_factory):
    """Seeds 0 and 1 trained together in one program (`seeds=2`)."""
    result = experiment.run(make_config(*TINY, "seeds=2"), tmp_path_factory.mktemp("vmapped"))
    return {r["seed"]: r for r in result.rows}


# make test-slow (40 s cold each): joblib's processes and submitit's local executor, the path a
# SLURM sweep takes (make test-slurm runs a real cluster); make test keeps the default launcher's
# sweeps above and below
@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["local_processes", "local_submitit"])
def test_other_launchers_run_a_sweep_with_the_vmapped_numbers(tmp_path, launcher, vmapped_seeds):
    hds_run_cli(
        "-m", *TINY, "seed=0,1", f"hydra/launcher={launcher}", f"hydra.sweep.dir={tmp_path}"
    )
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert sorted(r["seed"] for r in summary["rows"]) == [0, 1]
    for row in summary["rows"]:  # one job per seed gives what one program for both gave
        for key in ("sim_return", "real_return"):
            assert row[key] == pytest.approx(vmapped_seeds[row["seed"]][key], rel=1e-5)


def test_the_report_counts_solved_runs_and_costs_against_the_oracle():
    from hds.report import aggregate, markdown_table, relative_cost_table

    def row(method, gap, seed, real, plant="friction"):
        sim = -3.0
        return {
            "method": method,
            "plant": plant,
            "friction_gap": gap,
            "seed": seed,
            "sim_return": sim,
            "real_return": real,
            "gap": sim - real,
            "solved_sim": True,
            "solved_real": real >= -30,
        }

    rows = [row("oracle", g, s, -4.0 * (1 + g)) for g in (0.0, 1.0) for s in (0, 1)]
    rows += [row("pods_cl", 0.0, s, -6.0) for s in (0, 1)]
    rows += [row("pods_cl", 1.0, 0, -10.0), row("pods_cl", 1.0, 1, -50.0)]
    rows += [row(m, 1.0, s, -4.0, "gain") for m in ("oracle", "pods_cl") for s in (0, 1)]
    summary = aggregate(rows)
    table = markdown_table(summary)
    assert "| pods_cl | friction x1 | 2 | -3 [-3, -3] | -30 [" in table  # a plant at two gaps
    assert "| pods_cl | gain | 2 |" in table  # a plant at one
    friction_x1 = next(line for line in table.splitlines() if "| pods_cl | friction x1 |" in line)
    assert friction_x1.endswith("| 2, 1 |")  # solved on the simulator, on the plant
    table = relative_cost_table(summary)
    assert "| method | friction x0 | friction x1 | gain |" in table
    assert "| oracle | 1.00 | 1.00 | 1.00 |" in table
    assert "| pods_cl | 1.50 | 3.75 | 1.00 |" in table  # 6 / 4 and 30 / 8
    assert relative_cost_table([e for e in summary if e["method"] != "oracle"]) is None


def test_a_policy_is_evaluated_on_further_plants_and_reported_per_plant(tmp_path):
    """eval_plants (conf/real presets placed with `+real@eval_plants.<key>=<preset>`, at their
    own friction gap): one row per run and plant, the same simulator return, each plant's own
    real return; hds.report gives each plant its column, and a friction plant's rows the
    label, numbers and learning curves of a job swept over that gap."""
    from omegaconf import OmegaConf

    from hds.report import aggregate, animate_run, build, collect_rows, markdown_table
    from hds.report import main as report_main

    plants = ("gain", "delay", "friction_gain")
    at_gap_3 = ("+real@eval_plants.x3=mujoco", "eval_plants.x3.friction_gap=3")
    cfg = make_config(*TINY, "seeds=2", *(f"+real@eval_plants.{p}={p}" for p in plants), *at_gap_3)
    result = experiment.run(cfg, tmp_path / "once")
    own = {r["seed"]: r for r in result.rows}
    assert {r["plant"] for r in result.rows} == {"coulomb_friction@slider"}
    names = {"friction_gain": "friction+gain", "x3": "coulomb_friction@slider"}
    assert sorted((r["plant"], r["friction_gap"], r["seed"]) for r in result.rows_eval_plants) == (
        sorted(
            (names.get(p, p), 3.0 if p == "x3" else 1.0, s) for p in (*plants, "x3") for s in (0, 1)
        )
    )
    for r in result.rows_eval_plants:
        assert r["sim_return"] == own[r["seed"]]["sim_return"]
    reals = {(r["plant"], r["seed"]): r["real_return"] for r in result.rows_eval_plants}
    assert len(set(reals.values())) == len(reals)  # each plant its own dynamics
    report = build(tmp_path / "once").read_text()
    header = "| method | coulomb_friction@slider x1 | coulomb_friction@slider x3 | delay |"
    assert header in report
    # a sweep over the gap: the job at gap 1 (the same training, without eval_plants) and one at 3
    swept = tmp_path / "swept"
    (swept / "1").mkdir(parents=True)
    summary = json.loads((tmp_path / "once" / "summary.json").read_text())
    (swept / "1" / "summary.json").write_text(json.dumps({**summary, "rows_eval_plants": []}))
    alone = experiment.run(make_config(*TINY, "seeds=2", "real.friction_gap=3"), swept / "3")
    for r in alone.rows:  # the same as training there and evaluating on that plant alone
        assert reals[("coulomb_friction@slider", r["seed"])] == r["real_return"]
    friction_lines = lambda text: [  # noqa: E731
        line for line in text.splitlines() if line.startswith("| pods | coulomb_friction@slider")
    ]
    assert len(friction_lines(report)) == 2  # at gaps 1 and 3, mean and interval of 2 seeds
    swept_table = markdown_table(aggregate(collect_rows(swept)[0]))
    assert friction_lines(report) == friction_lines(swept_table)
    _, curves = collect_rows(tmp_path / "once")
    assert {column for _, column, _, _ in curves} >= {("coulomb_friction@slider", 3.0)}
    OmegaConf.save(OmegaConf.structured(cfg), tmp_path / "once" / "config.yaml")
    with pytest.raises(ValueError, match=r"gif_plant=x9: .* choose one of \['delay'"):
        animate_run(tmp_path / "once", eval_plant="x9")
    elsewhere = tmp_path / "report_elsewhere"
    for bad in (["gif=true", "gif_plant=x9"], ["gif_plant=x3"]):  # refused before writing
        with pytest.raises(ValueError, match="gif_plant"):
            report_main([f"dir={tmp_path / 'once'}", f"out={elsewhere}", *bad])
        assert not elsewhere.exists()
