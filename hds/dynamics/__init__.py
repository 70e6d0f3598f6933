"""Learned dynamics models for HDS: fitted on measured episodes, used as engines by the trainer.

  fit(cfg, env, obs, actions, key) -> (model, report)   cfg: hds.config.DynamicsConfig
  save(path, model, cfg, report) / load(path, env) -> model
  build(cfg, env, plant, key, out_dir) -> (model, report)   what `python -m hds.run` calls:
      load dynamics.path when given; else fit on dynamics.data, or on episodes collected
      from the plant with an excitation signal, and save the model to out_dir; the model is
      None when it predicts held-out data worse than the simulator (cfg.require_better)
  evaluate(model, obs, actions, ks)    open-loop k-step errors, model and constant velocity
  describe_errors(errors)    those errors on one line, as the log and hds.evaluate print them
  closed_loop_returns(model, task, act, starts, horizon, ctrl_range)   a policy's returns
      run through the model

A model (`DynamicsModel`) satisfies the engine protocol of hds.algo (reset, step, observe,
qqd; its state is the observation [q, qd]); see hds.dynamics.model for the three kinds.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import jax
import numpy as np

from hds.dynamics.metrics import closed_loop_returns, multistep_errors, open_loop_predictions
from hds.dynamics.model import (
    KINDS,
    DynamicsModel,
    Normalizer,
    constant_velocity,
    skeleton,
    zero_residual,
)
from hds.dynamics.store import load, read_meta, save
from hds.dynamics.training import as_arrays, evaluate, fit

log = logging.getLogger(__name__)


def excite(cfg, env, key) -> np.ndarray:
    """Open-loop controls [episodes, horizon, n_act]: the excitation signal, its amplitude
    spread evenly over episodes from excitation_scale / episodes up to excitation_scale, so
    the data hold both gentle and hard pushes."""
    from hds.data import excitation

    sim = env.sim
    u = excitation(cfg.excitation, key, cfg.episodes, cfg.horizon, sim.dt, sim.ctrl_range)
    middle = sim.ctrl_range.mean(1)
    scales = cfg.excitation_scale * np.arange(1, cfg.episodes + 1) / cfg.episodes
    return middle + scales[:, None, None] * (u - middle)


def collect_data(cfg, env, plant, key, controls=None):
    """A Dataset of cfg.episodes episodes recorded on `plant` from the task's initial states
    (hds.data.acquire.excited), driven by the excitation signal (`excite`), or by
    `controls(q0, qd0, signal)`: controls chosen from the episodes' initial states, `signal()`
    the excitation signal's."""
    from hds.data.acquire import excited

    def chosen(k_u, q0, qd0, deployed):
        def signal():
            return excite(cfg, env, k_u)

        return signal() if controls is None else controls(q0, qd0, signal)

    return excited(plant, env.task, key, cfg.episodes, cfg.horizon, chosen)


def measured_data(cfg, env, plant, key):
    """The data of the real plant that a model is fitted on (and that gap discovery reads):
    cfg.data when given, else cfg.episodes recorded on `plant`. Returns (Dataset, source)."""
    if cfg.data:
        from hds.data import load as load_data
        from hds.data import validate

        data = validate(load_data(cfg.data), env.sim, where=f"dynamics.data = {cfg.data}")
        return data, {"data": str(cfg.data)}
    if plant is None:
        raise ValueError(
            "fitting a dynamics model needs data: give dynamics.data (a "
            "measured dataset), dynamics.path (a fitted model) or a plant"
        )
    source = {
        "data": "plant",
        "excitation": cfg.excitation,
        "excitation_scale": cfg.excitation_scale,
    }
    return collect_data(cfg, env, plant, key), source


def _number(x: float | None) -> str:
    return "not finite" if x is None else f"{x:.3g}"


def describe_errors(errors: dict) -> str:
    """k-step nrmse (`evaluate`'s, or a report's "multistep") on one line:
    `k=1: model / constant velocity / simulator, k=10: ...`."""
    return ", ".join(
        f"k={k}: " + " / ".join(_number(row.get(n)) for n in ("model", "baseline", "simulator"))
        for k, row in errors.items()
    )


def worse_than_simulator(report: dict) -> str | None:
    """Why a fitted model has nothing to add: the k-step errors at which it predicts the
    held-out episodes no better than the simulator alone; None when it beats it at every k
    (or the report holds no simulator errors)."""
    worse = [
        f"k={k}: {_number(row['model'])} against {row['simulator']:.3g}"
        for k, row in report.get("multistep", {}).items()
        if row.get("simulator") is not None
        and (row["model"] is None or row["model"] >= row["simulator"])
    ]
    if not worse:
        return None
    return "open-loop nrmse on held-out episodes, model against simulator, " + ", ".join(worse)


def build(cfg, env, plant, key, out_dir) -> tuple[DynamicsModel | None, dict]:
    """The model for a run: loaded from cfg.path, or fitted (on cfg.data or on data collected
    from `plant`) and saved to out_dir. Returns (model, JSON-ready report); the model is None,
    and the report says why, when a fitted model predicts the held-out episodes no better
    than the simulator alone (cfg.require_better)."""
    if cfg.path:
        model = replace(load(cfg.path, env), gradient=cfg.gradient)
        meta = read_meta(cfg.path)
        log.info("loaded the %s dynamics model from %s", model.kind, cfg.path)
        if cfg.model not in ("none", model.kind):
            log.warning(
                "dynamics.model = %s, but the model at %s is a %s model: using it as saved",
                cfg.model,
                cfg.path,
                model.kind,
            )
        return model, {
            "path": str(Path(cfg.path).expanduser().absolute()),
            "loaded": True,
            **meta.get("report", {}),
        }
    k_data, k_fit = jax.random.split(key)
    data, source = measured_data(cfg, env, plant, k_data)
    model, report = fit(cfg, env, data, key=k_fit)
    model = replace(model, gradient=cfg.gradient)
    report.update(source)
    path = save(Path(out_dir), model, cfg, report)
    report.update({"path": str(path), "loaded": False})

    log.info(
        "fitted the %s dynamics model in %.1f s, saved to %s; open-loop nrmse on held-out "
        "episodes (model / constant velocity / simulator): %s",
        cfg.model,
        report["fit_s"],
        path,
        describe_errors(report["multistep"]),
    )
    why = worse_than_simulator(report) if cfg.require_better else None
    report["used"] = why is None
    if why:
        report["not_used_because"] = why
        log.warning(
            "the learned model is not used, its share of rollouts is 0: it predicts no better "
            "than the simulator (%s; dynamics.require_better=false uses it anyway)",
            why,
        )
        return None, report
    return model, report


__all__ = [
    "KINDS",
    "DynamicsModel",
    "Normalizer",
    "as_arrays",
    "build",
    "closed_loop_returns",
    "collect_data",
    "constant_velocity",
    "describe_errors",
    "evaluate",
    "excite",
    "fit",
    "load",
    "measured_data",
    "multistep_errors",
    "open_loop_predictions",
    "read_meta",
    "save",
    "skeleton",
    "worse_than_simulator",
    "zero_residual",
]
