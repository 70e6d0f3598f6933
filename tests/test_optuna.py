"""Hyperparameter search as Hydra users do it: hydra/sweeper=optuna (conf/experiment/optuna.yaml)
maximizes what `python -m hds.run` returns, and hds.report shows its trials."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml
from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from omegaconf import OmegaConf

from hds.config import CONF_DIR, compose
from tests.conftest import ROOT

ENV = {**os.environ, "WANDB_MODE": "offline"}


def hds_run(*args):
    proc = subprocess.run(
        [sys.executable, "-m", "hds.run", *args], cwd=ROOT, env=ENV, capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


def test_the_optuna_experiment_composes_a_maximizing_search():
    cfg = compose(["+experiment=optuna", "objective=sim_return"])
    assert (cfg.objective, cfg.noise.schedule, cfg.algo.improve_in) == (
        "sim_return",
        "exponential",
        "closed_loop",
    )
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        composed = hydra_compose("config", ["+experiment=optuna"], return_hydra_config=True)
    sweeper = OmegaConf.to_container(composed.hydra.sweeper)
    assert sweeper["_target_"].endswith("OptunaSweeper") and sweeper["direction"] == "maximize"
    assert set(sweeper["params"]) == {"algo.step_size", "noise.scale", "noise.decay"}
    with pytest.raises(ValueError, match="objective"):
        compose(["objective=return"])


def test_a_sweep_in_an_experiment_that_is_a_multirun_needs_no_dash_m():
    """+experiment=optuna sets hydra.mode: MULTIRUN, so a sweep on its command line is its
    search space, not a forgotten -m; a choice() with a value out of range is refused before
    any trial, as the basic sweeper's values are; without such an experiment, -m is asked for."""
    from hds.commands import invalid_jobs

    assert invalid_jobs(["+experiment=optuna", "noise.decay=choice(0.5,0.9)"]) == []
    refused = invalid_jobs(["+experiment=optuna", "noise.decay=choice(0.5,2.0)"])
    assert "noise.decay = 2.0 is out of range" in refused[0] and "none launched" in refused[-1]
    assert "add -m" in invalid_jobs(["method=pods_cl", "noise.decay=0.5,0.9"])[0]


@pytest.mark.slow  # three trials of a tiny run: ~1 min on 2 cores
def test_three_optuna_trials_maximize_the_returned_real_return(tmp_path):
    """Three trials of a decay drawn from an interval reaching out of range (a trial drawn
    past 1 fails in its job, before anything compiles; a choice() of values is checked before
    any trial, as the basic sweeper's values are): the study's best is the best finished
    trial's mean real return, the failed trial is recorded and the study goes on, and
    hds.report lists the finished trials, best first."""
    out = tmp_path / "study"
    hds_run(
        "+experiment=optuna", "debug=fast", "seeds=2", "logger=none",
        "hydra.sweeper.n_trials=3", "noise.decay=interval(0.2,1.2)", f"hydra.sweep.dir={out}",
    )  # fmt: skip
    study = yaml.safe_load((out / "optimization_results.yaml").read_text())
    trials, failed = {}, []
    for job in sorted(p for p in out.iterdir() if p.is_dir() and p.name.isdigit()):
        overrides = yaml.safe_load((job / ".hydra" / "overrides.yaml").read_text())
        sampled = dict(o.split("=", 1) for o in overrides)
        if (job / "failed.txt").is_file():
            assert float(sampled["noise.decay"]) > 1.0
            assert "is out of range: it must lie in [0.0, 1.0]" in (job / "failed.txt").read_text()
            failed.append(job.name)
            continue
        rows = json.loads((job / "summary.json").read_text())["rows"]
        assert {r["seed"] for r in rows} == {0, 1} and {r["method"] for r in rows} == {"pods_cl"}
        assert 0.2 <= float(sampled["noise.decay"]) <= 1.0
        step = float(sampled["algo.step_size"])
        trials[job.name] = (step, np.mean([r["real_return"] for r in rows]))
    assert len(trials) + len(failed) == 3 and trials and failed  # TPE's seed 0 draws both
    best = max(trials.values(), key=lambda t: t[1])
    assert study["best_value"] == pytest.approx(best[1], rel=1e-6)
    assert study["best_params"]["algo.step_size"] == pytest.approx(best[0])
    assert all(0.005 <= s <= 0.2 for s, _ in trials.values())
    # the report: the study's best, and a row per finished trial, best first
    proc = subprocess.run(
        [sys.executable, "-m", "hds.report", f"dir={out}"], cwd=ROOT, env=ENV, capture_output=True
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    report = (out / "report.md").read_text()
    section = report[report.index("### Optuna study") :]
    assert f"algo.step_size={best[0]:.4g}" in section
    rows = [line for line in section.splitlines() if line.startswith("| ") and "---" not in line]
    assert len(rows) == 1 + len(trials)  # the heading, then the finished trials
    assert rows[1].startswith("| " + max(trials, key=lambda j: trials[j][1]) + " |")
