"""`python -m experiments.excitation_design`: plant time to a given interval width with an
excitation designed through the differentiable simulator (hds.discover.design) against random
steps, PRBS and a chirp of the same amplitude bound; and the widths the design predicted
against those the fit achieved. Writes results.json, results.md and width_vs_time.png here.

  --cases friction80,friction_gain,friction80_own_laws   --repeats 5
  (furuta: XLA_FLAGS=--xla_cpu_use_fusion_emitters=false ... --cases furuta)
  --criterion asked (default: the case's asked widths, weighted A-optimal) | D | A
  --mismatch none (default) | calibrated | raw: the law mismatch the design's criterion holds
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from scipy import stats

from hds.config import env_config
from hds.data import collect
from hds.data.excitation import excitation
from hds.discover.data import noise_level
from hds.discover.design import (
    WindowFit,
    calibrated,
    get_designer,
    half_width,
    limits_of,
    typical_scale,
    with_mismatch,
)
from hds.discover.workflow import fit_backend, with_backend
from hds.envs import make_env
from hds.real import make_plant
from hds.utils.io import atomic_write_bytes, atomic_write_json
from hds.utils.runtime import enable_compilation_cache

HERE = Path(__file__).resolve().parent
CONF = Path(__file__).resolve().parents[2] / "hds" / "conf"
SIGNALS = ("designed", "steps", "prbs", "chirp")
ROUNDS = (2, 2, 4, 8)  # episodes recorded per round: cumulative 2, 4, 8, 16
AMPLITUDE = 0.5  # every signal's bound: half the actuator's half range about the middle

CASES = {
    # 80 N of rail friction: real=mujoco with real.friction_gap=4 (20 N x 4)
    "friction80": {
        "env": "cartpole_balance",
        "real": {
            "plant": "mujoco",
            "friction_gap": 4.0,
            "effects": [
                {"name": "coulomb_friction", "target": "slider", "params": {"force": 20.0}}
            ],
        },
        "rest": [0.0, 3.141592653589793],  # cart centred, pole hanging
        "keys": ["coulomb_friction@slider"],
        "targets": {"coulomb_friction@slider.force": 0.05},
        "noise": [1e-3, 2e-3, 1e-2, 2e-2],  # m, rad, m/s, rad/s
    },
    # the two-effect plant (hds/conf/real/friction_gain.yaml): 20 N and a motor 20% weaker
    "friction_gain": {
        "env": "cartpole_balance",
        "real": {
            "plant": "mujoco",
            "friction_gap": 1.0,
            "effects": [
                {"name": "coulomb_friction", "target": "slider", "params": {"force": 20.0}},
                {"name": "actuator_gain", "target": "slide", "params": {"gain": 0.8}},
            ],
        },
        "rest": [0.0, 3.141592653589793],
        "keys": ["coulomb_friction@slider", "actuator_gain@slide"],
        "targets": {"coulomb_friction@slider.force": 0.05, "actuator_gain@slide.gain": 0.03},
        "noise": [1e-3, 2e-3, 1e-2, 2e-2],
    },
    # the control: 80 N on a plant with the simulator's own laws (tanh friction, the fit's
    # backend): no law mismatch, sensor noise alone, what the prediction models
    "friction80_own_laws": {
        "env": "cartpole_balance",
        "plant": "simulator",
        "real": {
            "plant": "brax",
            "friction_gap": 4.0,
            "effects": [
                {"name": "coulomb_friction", "target": "slider", "params": {"force": 20.0}}
            ],
        },
        "rest": [0.0, 3.141592653589793],
        "keys": ["coulomb_friction@slider"],
        "targets": {"coulomb_friction@slider.force": 0.05},
        "noise": [1e-3, 2e-3, 1e-2, 2e-2],
    },
    # the Furuta (QUBE-Servo 2): a motor 20% weaker and dry friction on the arm (8% of the
    # motor's 0.025 N m)
    "furuta": {
        "env": "furuta_balance",
        "real": {
            "plant": "mujoco",
            "friction_gap": 1.0,
            "effects": [
                {"name": "actuator_gain", "target": "motor", "params": {"gain": 0.8}},
                {"name": "coulomb_friction", "target": "arm", "params": {"force": 0.002}},
            ],
        },
        "rest": [0.0, 3.141592653589793],  # pendulum hanging
        "keys": ["actuator_gain@motor", "coulomb_friction@arm"],
        "targets": {"actuator_gain@motor.gain": 0.03, "coulomb_friction@arm.force": 0.05},
        "noise": [2e-3, 2e-3, 5e-2, 5e-2],  # rad (an encoder's 2048 counts), rad/s
    },
}


class NoisyPlant:
    """A plant whose observations carry white Gaussian sensor noise of std `noise` [n_obs]."""

    def __init__(self, plant, noise, seed):
        self.plant, self.noise = plant, np.asarray(noise, np.float64)
        self.rng = np.random.default_rng(seed)
        for name in ("obs_names", "action_names", "dt", "ctrl_range"):
            setattr(self, name, getattr(plant, name))

    def _noisy(self, obs):
        return obs + self.rng.normal(size=obs.shape) * self.noise

    def reset(self, q, qd):
        return self._noisy(self.plant.reset(q, qd))

    def step(self, u):
        return self._noisy(self.plant.step(u))

    def state(self):
        return self.plant.state()


def worst(values, half, labels, targets) -> float:
    """max over the targeted parameters of (relative half-width / its target): <= 1 reached."""
    out = 0.0
    for label, t in targets.items():
        i = labels.index(label)
        out = max(out, float(half[i]) / max(abs(float(values[i])), 1e-12) / t)
    return out


def time_to_target(seconds, ratio) -> tuple[float, bool]:
    """Plant seconds at which the ratio (width / target) reaches 1: log-log interpolation
    between recorded amounts; past the last, extrapolated as 1/sqrt(time) (flagged)."""
    s, r = np.log(np.asarray(seconds)), np.log(np.maximum(np.asarray(ratio), 1e-12))
    if not np.all(np.isfinite(r)):
        finite = np.isfinite(r)
        s, r = s[finite], r[finite]
        if len(s) == 0:
            return math.inf, True
    if r[0] <= 0:  # reached at the first amount: extrapolate back as 1/sqrt(time)
        return float(np.exp(s[0] + 2 * r[0])), False
    for i in range(1, len(s)):
        if r[i] <= 0:
            f = r[i - 1] / (r[i - 1] - r[i])
            return float(np.exp(s[i - 1] + f * (s[i] - s[i - 1]))), False
    return float(np.exp(s[-1] + 2 * r[-1])), True


def case_plant(spec, env_cfg, fit_cfg):
    """The case's plant (noise-free; `NoisyPlant` adds the sensors')."""
    real = OmegaConf.create(spec["real"])
    if spec.get("plant") == "simulator":  # the fit's own simulator, its smoothed laws
        from hds.real.brax_plant import BraxPlant

        return BraxPlant(
            make_env(fit_cfg, effects=list(real.effects), friction_gap=real.friction_gap)
        )
    return make_plant(real, env_cfg)


def run_case(
    name,
    spec,
    repeats,
    log,
    criterion="asked",
    parameterisation="per_step",
    iterations=(200, 100),
    signals=SIGNALS,
    mismatch="none",
    repeat_from=0,
    drag="off",
):
    env_cfg = env_config(
        OmegaConf.to_container(OmegaConf.load(CONF / "env" / f"{spec['env']}.yaml"))
    )
    fit_cfg = with_backend(env_cfg, fit_backend(env_cfg, "auto"))
    env = make_env(env_cfg)
    task, steps = env.task, int(env.task.horizon)
    dt = float(env.sim.dt)
    t0 = time.perf_counter()
    designer = get_designer(fit_cfg, spec["keys"], dt, steps, horizon=10)
    fitter = WindowFit(designer, sum(ROUNDS))
    limits = limits_of(fit_cfg, AMPLITUDE)
    labels, targets = designer.labels, spec["targets"]
    # every episode of every signal starts at rest (a sysid run on a rig starts from rest):
    # the pole hanging, predictable; from the balance task's upright states the first fall
    # decides the whole record and no design made before it holds
    x0 = np.concatenate([np.asarray(spec["rest"]), np.zeros(env.sim.n_obs - env.sim.nq)])
    start = np.array(designer.model.start, np.float64)
    theta_nominal = designer.theta(None)
    theta0 = theta_nominal.copy()
    theta0[designer.slots] = start[designer.slots]
    plant_base = case_plant(spec, env_cfg, fit_cfg)
    truth = {}
    for e in spec["real"]["effects"]:
        for p, v in e["params"].items():
            scale = spec["real"]["friction_gap"] if e["name"] == "coulomb_friction" else 1.0
            truth[f"{e['name']}@{e['target']}.{p}"] = v * scale
    truth_estimate = {}
    for label, v in truth.items():
        key_, p = label.rsplit(".", 1)
        truth_estimate.setdefault(key_, {})[p] = v
    truth_values = np.array([truth[label] for label in labels])
    # the friction's joint velocity: how much of the record slides (friction's information)
    friction = next(k for k in spec["keys"] if k.startswith("coulomb_friction"))
    slide_index = list(env.sim.obs_names).index("qd_" + friction.split("@")[1])

    def standard(seed, episodes) -> dict:
        """Each standard signal of the amplitude bound, [episodes, T, n_act] ([T, n_act] for
        one episode: a round's rivals of the design)."""
        out = {}
        for sig in SIGNALS[1:]:
            params = {"bit_time": 4 * dt} if sig == "prbs" else {}
            u = excitation(
                sig,
                seed,
                episodes,
                steps,
                dt,
                np.asarray(env.sim.ctrl_range),
                scale=AMPLITUDE,
                **params,
            )
            out[sig] = u[0] if episodes == 1 else u
        return out

    rows = []
    for rep in range(repeat_from, repeats):
        plant = NoisyPlant(plant_base, spec["noise"], 1000 + rep)
        q0 = np.tile(x0[: env.sim.nq], (sum(ROUNDS), 1))
        qd0 = np.zeros((sum(ROUNDS), env.sim.n_obs - env.sim.nq))
        for signal in signals:
            ts = time.perf_counter()
            cum, ratios, fits, predicted = [], [], [], []
            applied_gap, all_ctrl, chosen, predicted_now, noise_est = 0.0, [], [], [], []
            noise_diff = []
            if signal == "designed":
                obs, acts, estimate, noise, design, infos = [], [], None, None, None, []
                used = 0
                # the law mismatch measured so far (Designer.mismatch, calibrated to the fit's
                # noise part); none before the first record
                mis = {"raw": None, "calibrated": None}
                pred_mis, pred_mis_raw, mis_scale, mis_size = [], [], [], []
                # the law mismatch's mean measured so far (Designer.mismatch_mean) and what it
                # predicts: the pooled estimate's shift and the noise part with the drags
                mean, pred_drag, shift_pred, shift_design = None, [], [], []
                for r, n in enumerate(ROUNDS):
                    design = designer.design(
                        estimate,
                        x0,
                        noise,
                        limits,
                        iterations=iterations[0] if r == 0 else iterations[1],
                        seed=rep,
                        start=design,
                        criterion=targets if criterion == "asked" else criterion,
                        rivals=standard(104729 * rep + r + 1, 1),
                        parameterisation=parameterisation,
                        mismatch=mis.get(mismatch),
                        mismatch_mean=mean if drag == "on" else None,
                        # the pooled estimate's bias is this round's drag times its share,
                        # n / (used + n), its variance the record's over used + n episodes:
                        # the squared drag weighs n^2 / (used + n) per-episode variances
                        episodes=n * n / (used + n),
                    )
                    chosen.append(design.signal)
                    ctrl = np.repeat(design.controls()[None], n, axis=0)
                    # the widths after this round, predicted before it: every round's controls
                    # so far at the current estimate and noise (the first round's assumed
                    # noise and nominal parameters replaced once data exist)
                    if estimate is not None:
                        u_so_far = np.concatenate([*all_ctrl, ctrl])
                        se_all = designer.predicted_se_of(estimate, u_so_far, x0, noise)
                        predicted_now.append(half_width(se_all, used + n).tolist())
                        # the same with the mismatch measured so far (raw and calibrated)
                        for key_, out_ in (("calibrated", pred_mis), ("raw", pred_mis_raw)):
                            se_m = designer.predicted_se_of(
                                estimate, u_so_far, x0, noise, mismatch=mis[key_]
                            )
                            out_.append(half_width(se_m, used + n).tolist())
                        dragged = designer.drag_of(estimate, u_so_far, x0, noise, mean)
                        pred_drag.append(half_width(dragged["se"], used + n).tolist())
                        shift_pred.append(dragged["shift"].tolist())
                        design_drag = designer.drag_of(estimate, ctrl, x0, noise, mean)
                        shift_design.append(design_drag["shift"].tolist())
                    else:
                        predicted_now.append(design.predicted_half(n).tolist())
                        pred_mis.append(predicted_now[-1])
                        pred_mis_raw.append(predicted_now[-1])
                        pred_drag.append(predicted_now[-1])
                        shift_pred.append([0.0] * len(labels))
                        shift_design.append([0.0] * len(labels))
                    ds = collect(plant, task, q0[used : used + n], qd0[used : used + n], ctrl)
                    # the controls the plant applied are the designed ones (open loop, within
                    # the bound: nothing clips or distorts them on the way)
                    applied_gap = max(applied_gap, float(np.abs(ds.actions - ctrl).max()))
                    all_ctrl.append(ctrl)
                    used += n
                    obs.append(ds.obs)
                    acts.append(ds.actions)
                    infos.append((n, design.predicted_se))
                    o, a = np.concatenate(obs), np.concatenate(acts)
                    fit = fitter(o, a, theta0)
                    estimate = {}
                    for k_, v in zip(labels, fit["values"], strict=True):
                        key_, p = k_.rsplit(".", 1)
                        estimate.setdefault(key_, {})[p] = float(v)
                    # the sensor noise from the fit's one-step residuals (Designer.sensor_noise);
                    # the measurements' differences (noise_level) hold the motion too
                    noise = fit["noise"]
                    noise_diff.append((noise_level(o) / np.asarray(spec["noise"])).tolist())
                    noise_est.append((noise / np.asarray(spec["noise"])).tolist())
                    mis["raw"] = designer.mismatch(fit["theta"], o, a, noise)
                    mis["calibrated"] = calibrated(
                        designer, mis["raw"], fit["theta"], o, a, noise, fit["noise_half"]
                    )
                    mis_scale.append(mis["calibrated"].scale)
                    mean = designer.mismatch_mean(fit["theta"], o, a, noise)
                    # its size: the mean variance over the record, per signal, over the noise's
                    var = mis["raw"].variance(o[:, :-1], a).reshape(-1, o.shape[-1]).mean(0)
                    mis_size.append((np.sqrt(var) / np.maximum(noise, 1e-12)).tolist())
                    # the rounds' designs together: precisions add, t over all episodes
                    prec = sum(n_ / se**2 for n_, se in infos)
                    predicted.append(half_width(np.sqrt(used / prec), used).tolist())
                    cum.append(used * steps * dt)
                    fits.append(fit)
            else:
                u = standard(7919 * rep + 1, sum(ROUNDS))[signal]
                ds = collect(plant, task, q0, qd0, u)
                applied_gap = float(np.abs(ds.actions - u).max())
                all_ctrl.append(u)
                used = 0
                for n in ROUNDS:
                    used += n
                    fits.append(fitter(ds.obs[:used], ds.actions[:used], theta0))
                    cum.append(used * steps * dt)
            # the model's prediction of every signal's widths at the truth, with the noise
            # the sensors have (the same model and noise model for every signal): how much
            # plant time the design saves if the plant had the simulator's laws
            u_all = np.concatenate(all_ctrl)
            se = designer.predicted_se_of(truth_estimate, u_all, x0, spec["noise"])
            n_all = len(u_all)
            model_half = se * stats.t.ppf(0.975, n_all - 1) / np.sqrt(n_all)
            model_ratio = worst(truth_values, model_half, labels, targets)
            recorded = np.concatenate(obs) if signal == "designed" else ds.obs
            applied = np.concatenate(acts) if signal == "designed" else ds.actions
            # the sensor-noise part on the record the plant gave: the design's prediction made
            # at the fit's estimate and measured noise on the recorded trajectories (what the
            # fit's noise part would be if its residuals were that noise alone)
            sensor_half = []
            for fit, n in zip(fits, np.cumsum(ROUNDS), strict=True):
                se_rec = designer.record_se(fit["theta"], recorded[:n], applied[:n], fit["noise"])
                sensor_half.append((stats.t.ppf(0.975, n - 1) * se_rec).tolist())
            qd = recorded[..., slide_index]
            sliding = float(np.mean(np.abs(qd) > 1.0 / fit_cfg.sharpness))
            noise_ratios = []
            for fit in fits:
                ratios.append(worst(fit["values"], fit["half"], labels, targets))
                noise_ratios.append(worst(fit["values"], fit["noise_half"], labels, targets))
            reach, extrapolated = time_to_target(cum, noise_ratios)
            reach_full, extrapolated_full = time_to_target(cum, ratios)
            row = {
                "case": name,
                "repeat": rep,
                "signal": signal,
                "seconds": cum,
                "ratio": noise_ratios,  # the noise part of the intervals
                "ratio_reported": ratios,  # with the law-mismatch part
                "time_to_target_reported": reach_full,
                "extrapolated_reported": extrapolated_full,
                "values": [f["values"].tolist() for f in fits],
                "half": [f["half"].tolist() for f in fits],
                "noise_half": [f["noise_half"].tolist() for f in fits],
                "predicted_half": predicted,
                "sensor_half": sensor_half,
                "noise_over_true": [
                    (f["noise"] / np.asarray(spec["noise"])).tolist() for f in fits
                ],
                "residual_over_noise": [f["residual_over_noise"] for f in fits],
                "time_to_target": reach,
                "extrapolated": extrapolated,
                "wall_s": time.perf_counter() - ts,
                "applied_minus_planned": applied_gap,
                "chosen": chosen,  # per round: the design, or the rival the model preferred
                "predicted_half_now": predicted_now,
                "noise_estimate_over_true": noise_est,
                "noise_differences_over_true": noise_diff,
                "model_half": model_half.tolist(),
                "model_ratio": model_ratio,
                "sliding_share": sliding,
            }
            if signal == "designed":
                row["parameterisation"], row["iterations"] = parameterisation, list(iterations)
                row["mismatch"] = mismatch  # which mismatch model the design's criterion held
                row["predicted_half_now_mismatch"] = pred_mis
                row["predicted_half_now_mismatch_raw"] = pred_mis_raw
                row["mismatch_scale"] = mis_scale  # the calibration factor per round's fit
                row["mismatch_std_over_noise"] = mis_size
                row["drag"] = drag  # whether the criterion held the mismatch mean's drag
                # per round, predicted before it: the noise part with the drags' scatter, the
                # pooled estimate's shift (against values[j] - values[j - 1]) and the round's
                # own signal's shift alone
                row["predicted_half_now_drag"] = pred_drag
                row["predicted_shift"] = shift_pred
                row["predicted_shift_round"] = shift_design
                # the predictions are typical (median) widths: `half_width`'s typical_scale
                row["typical"] = True
            rows.append(row)
            log(
                f"{name} rep {rep} {signal}: ratio {np.round(noise_ratios, 3).tolist()} "
                f"reported {np.round(ratios, 3).tolist()} "
                f"reach {reach:.3g} s{' (extrapolated)' if extrapolated else ''} "
                f"values {np.round(fits[-1]['values'], 4).tolist()} ({row['wall_s']:.1f} s)"
            )
    return {
        "labels": labels,
        "targets": targets,
        "truth": truth,
        "rows": rows,
        "wall_s": time.perf_counter() - t0,
        "episode_seconds": steps * dt,
    }


def anchored_time(row, key="ratio") -> float:
    """Plant seconds to the target by the 1/sqrt(time) law through the width of the most data
    (16 episodes): T x ratio^2. The widths of 2 episodes (a t quantile of 12.7 on a variance
    from 2 clusters) are too noisy to interpolate between."""
    return float(row["seconds"][-1] * row[key][-1] ** 2)


def carried_over(rows, j: int, n: int, i: int, key=None) -> tuple[float, float]:
    """Round j's parameter i (n episodes): medians over the repeats `rows` of the predicted
    noise part and reported width over the achieved, with what the fit so far measured
    carried to the new record (with_mismatch; round 0 has no data: the sensor part alone),
    the noise part predicted with the mismatch model `key` if any."""
    noise_ratio, full_ratio = [], []
    for r in rows:
        before = (
            (r["sensor_half"][j - 1], r["noise_half"][j - 1], r["half"][j - 1])
            if j
            else (None, None, None)
        )
        pn, pf = with_mismatch(
            r["predicted_half_now"][j],
            n,
            *before,
            int(np.cumsum(ROUNDS)[j - 1]) if j else 0,
            noise_predicted=None if key is None else r[key][j],
        )
        noise_ratio.append(pn[i] / r["noise_half"][j][i])
        full_ratio.append(pf[i] / r["half"][j][i])
    return float(np.median(noise_ratio)), float(np.median(full_ratio))


def summarise(results) -> tuple[str, dict]:
    lines, summary = [], {}
    for key, what in (("ratio", "noise part"), ("ratio_reported", "reported, with law mismatch")):
        lines.append(
            f"**Intervals: {what}.** Width / target at 16 episodes (worst targeted "
            "parameter; 1 = reached) and the plant seconds to the target by "
            "1/sqrt(time) through it; median [min, max] over repeats."
        )
        lines.append("")
        lines.append(
            "| case | signal | width / target at 16 episodes | plant s to target | "
            "reached by 16 episodes |"
        )
        lines.append("| --- | --- | --- | --- | --- |")
        ratios = []
        for case, res in results.items():
            by = {}
            for s in SIGNALS:
                rows = [r for r in res["rows"] if r["signal"] == s]
                w = np.array([r[key][-1] for r in rows])
                t = np.array([anchored_time(r, key) for r in rows])
                by[s] = float(np.median(t))
                lines.append(
                    f"| {case} | {s} | {np.median(w):.3f} [{w.min():.3f}, {w.max():.3f}] | "
                    f"{np.median(t):.3g} [{t.min():.3g}, {t.max():.3g}] | "
                    f"{int(np.sum(w <= 1))}/{len(rows)} |"
                )
            best = min(by[s] for s in SIGNALS if s != "designed")
            ratios.append(best / by["designed"])
            summary.setdefault(case, {})[key] = {
                "median_time": by,
                "best_standard_over_designed": ratios[-1],
            }
        summary[f"median_ratio_{key}"] = float(np.median(ratios))
        lines.append("")
        lines.append("| case | best standard signal's plant time / designed's |")
        lines.append("| --- | --- |")
        for case, r in zip(results, ratios, strict=True):
            lines.append(f"| {case} | {r:.2f} |")
        lines.append(f"| median over cases | {np.median(ratios):.2f} |")
        lines.append("")
    # the model's view: every signal's widths predicted at the truth (plant time to the
    # target by 1/sqrt(time): T x ratio^2), and what the record shows about why
    lines.append(
        "**The model's prediction per signal** (at the true values, sensor noise alone, the "
        "record's own controls; median over repeats): predicted plant s to the target, "
        "achieved noise-part half-width / predicted at 16 episodes per parameter, the share of "
        "steps the friction's joint slides (|v| > 1/sharpness), and the largest |applied - "
        "planned| control."
    )
    lines.append("")
    lines.append(
        "| case | signal | predicted plant s to target | achieved / predicted half | "
        "sliding share | applied - planned |"
    )
    lines.append("| --- | --- | --- | --- | --- | --- |")
    model_ratios, paired = [], []
    for case, res in results.items():
        if "model_ratio" not in res["rows"][0]:
            continue
        by = {}
        for s in SIGNALS:
            rows = [r for r in res["rows"] if r["signal"] == s]
            t = np.median([r["seconds"][-1] * r["model_ratio"] ** 2 for r in rows])
            by[s] = t
            achieved = np.median(
                [np.array(r["noise_half"][-1]) / np.array(r["model_half"]) for r in rows], axis=0
            )
            lines.append(
                f"| {case} | {s} | {t:.3g} | "
                + ", ".join(f"{a:.2f}" for a in achieved)
                + f" | {np.median([r['sliding_share'] for r in rows]):.2f} | "
                f"{max(r['applied_minus_planned'] for r in rows):.1e} |"
            )
        model_ratios.append(min(by[s] for s in SIGNALS if s != "designed") / by["designed"])
        # paired by repeat (same plant noise seed): best standard's time / designed's
        reps = sorted({r["repeat"] for r in res["rows"] if r["signal"] == "designed"})
        per = []
        for k in reps:
            rows = {r["signal"]: r for r in res["rows"] if r["repeat"] == k}
            best = min(anchored_time(rows[s]) for s in SIGNALS if s != "designed")
            per.append(best / anchored_time(rows["designed"]))
        paired.append((case, per))
    if model_ratios:
        lines.append("")
        lines.append(
            "| case | predicted: best standard's plant time / designed's | achieved (noise "
            "part), per repeat: median [min, max] |"
        )
        lines.append("| --- | --- | --- |")
        for (case, per), m in zip(paired, model_ratios, strict=True):
            lines.append(
                f"| {case} | {m:.2f} | {np.median(per):.2f} [{min(per):.2f}, {max(per):.2f}] |"
            )
        lines.append(f"| median over cases | {np.median(model_ratios):.2f} | |")
        lines.append("")
        summary["median_predicted_ratio"] = float(np.median(model_ratios))
    # predicted against achieved
    lines.append(
        "**Predicted against achieved** (designed signal, median over repeats; the "
        "prediction is of the noise part)."
    )
    lines.append("")
    lines.append(
        "| case | parameter | episodes | predicted half | achieved (noise part) | "
        "achieved (reported) | predicted / achieved noise part | every round at the "
        "current estimate and noise, / achieved | that x the last fit's residual / noise, "
        "/ achieved | achieved sensor part (the record) | every round at the current "
        "estimate and noise, / sensor part | sensor part / noise part | with the mismatch "
        "carried from the fit so far, / achieved noise part | that, / achieved reported | "
        "with the mismatch model (calibrated), / achieved noise part | that plus the carried "
        "law-mismatch part, / achieved reported | the mismatch model uncalibrated, / achieved "
        "noise part | that, / achieved reported | with the mismatch mean's drags "
        "(`drag_of`), / achieved noise part | that plus the carried law-mismatch part, / "
        "achieved reported |"
    )
    lines.append("| --- " * 20 + "|")
    errors, errors_inflated, errors_now, errors_like = [], [], [], []
    errors_carried, errors_carried_full = [], []
    model_errors = {"calibrated": ([], []), "raw": ([], []), "drag": ([], [])}
    for case, res in results.items():
        rows = [r for r in res["rows"] if r["signal"] == "designed"]
        for i, label in enumerate(res["labels"]):
            for j, n in enumerate(np.cumsum(ROUNDS)):
                pred = np.median([r["predicted_half"][j][i] for r in rows])
                noise = np.median([r["noise_half"][j][i] for r in rows])
                full = np.median([r["half"][j][i] for r in rows])
                errors.append(pred / noise)
                now = ""
                if "predicted_half_now" in rows[0]:
                    ratio_now = np.median(
                        [r["predicted_half_now"][j][i] / r["noise_half"][j][i] for r in rows]
                    )
                    errors_now.append(ratio_now)
                    now = f"{ratio_now:.2f}"
                inflated = ""
                if "residual_over_noise" in rows[0]:
                    # known when the round is designed: the fit before it (none before the first)
                    infl = np.median(
                        [
                            r.get("predicted_half_now", r["predicted_half"])[j][i]
                            * (r["residual_over_noise"][j - 1] if j else 1.0)
                            / r["noise_half"][j][i]
                            for r in rows
                        ]
                    )
                    errors_inflated.append(infl)
                    inflated = f"{infl:.2f}"
                sensor = like = share = ""
                if "sensor_half" in rows[0]:
                    sens = np.median([r["sensor_half"][j][i] for r in rows])
                    # the sensor part on the record is no draw over episodes: like with like is
                    # the prediction without its typical scale
                    like_v = np.median(
                        [
                            r["predicted_half_now"][j][i]
                            / (typical_scale(int(n)) if r.get("typical") else 1.0)
                            / r["sensor_half"][j][i]
                            for r in rows
                        ]
                    )
                    share_v = np.median(
                        [r["sensor_half"][j][i] / r["noise_half"][j][i] for r in rows]
                    )
                    errors_like.append(like_v)
                    sensor, like, share = f"{sens:.3g}", f"{like_v:.2f}", f"{share_v:.2f}"

                carried = carried_full = ""
                if "sensor_half" in rows[0]:
                    cn, cf = carried_over(rows, j, int(n), i)
                    errors_carried.append(cn)
                    errors_carried_full.append(cf)
                    mark = "" if j else " (noise only)"
                    carried, carried_full = f"{cn:.2f}{mark}", f"{cf:.2f}{mark}"
                modelled = []
                for kind, key_ in (
                    ("calibrated", "predicted_half_now_mismatch"),
                    ("raw", "predicted_half_now_mismatch_raw"),
                    ("drag", "predicted_half_now_drag"),
                ):
                    if not all(key_ in r for r in rows):
                        modelled += ["", ""]
                        continue
                    # the noise part predicted with the mismatch measured so far; the reported
                    # width adds the law-mismatch part carried from the fit so far
                    mn, mf = carried_over(rows, j, int(n), i, key_)
                    model_errors[kind][0].append(mn)
                    model_errors[kind][1].append(mf)
                    mark = "" if j else " (noise only)"
                    modelled += [f"{mn:.2f}{mark}", f"{mf:.2f}{mark}"]
                lines.append(
                    f"| {case} | {label} | {n} | {pred:.3g} | {noise:.3g} | {full:.3g} | "
                    f"{pred / noise:.2f} | {now} | {inflated} | {sensor} | {like} | {share} | "
                    f"{carried} | {carried_full} | " + " | ".join(modelled) + " |"
                )
    summary["predicted_over_achieved"] = [float(x) for x in errors]
    lines.append("")
    # each comparison's share of cells within 30% (the first always, the others where measured)
    shares = [
        (
            "share_within_30pct",
            errors,
            "Predicted within 30% of the achieved noise part: {:.0%} of {} (case, parameter, "
            "amount) cells.",
        ),
        (
            "share_within_30pct_current",
            errors_now,
            "Every round predicted at the current estimate and measured noise: {:.0%} of {} cells "
            "within 30%.",
        ),
        (
            "share_within_30pct_sensor_part",
            errors_like,
            "Like with like (every round at the current estimate and measured noise against the "
            "sensor part on the record): {:.0%} of {} cells within 30%.",
        ),
        (
            "share_within_30pct_residual_level",
            errors_inflated,
            "With the last fit's residual level as the noise: {:.0%} of {} cells within 30%.",
        ),
        (
            "share_within_30pct_carried",
            errors_carried,
            "With the mismatch carried from the fit so far (`with_mismatch`; round 0: the sensor "
            "part alone), against the achieved noise part: {:.0%} of {} cells within 30%.",
        ),
        (
            "share_within_30pct_carried_reported",
            errors_carried_full,
            "The same, noise part plus law-mismatch part, against the achieved reported "
            "half-width: {:.0%} of {} cells within 30%.",
        ),
        (
            "share_within_30pct_mismatch_model",
            model_errors["calibrated"][0],
            "With the mismatch model measured so far (`Designer.mismatch`, `calibrated`; round "
            "0: the sensor part alone), against the achieved noise part: {:.0%} of {} cells "
            "within 30%.",
        ),
        (
            "share_within_30pct_mismatch_model_reported",
            model_errors["calibrated"][1],
            "The same plus the carried law-mismatch part, against the achieved reported "
            "half-width: {:.0%} of {} cells within 30%.",
        ),
        (
            "share_within_30pct_mismatch_raw",
            model_errors["raw"][0],
            "The mismatch model uncalibrated (a white disturbance of the one-step residuals' "
            "size), against the achieved noise part: {:.0%} of {} cells within 30%.",
        ),
        (
            "share_within_30pct_mismatch_raw_reported",
            model_errors["raw"][1],
            "The same, against the achieved reported half-width: {:.0%} of {} cells within 30%.",
        ),
        (
            "share_within_30pct_drag",
            model_errors["drag"][0],
            "With the mismatch mean's drags (`Designer.drag_of`: sensor noise plus the episodes' "
            "predicted shifts' scatter; round 0: the sensor part alone), against the achieved "
            "noise part: {:.0%} of {} cells within 30%.",
        ),
        (
            "share_within_30pct_drag_reported",
            model_errors["drag"][1],
            "The same plus the carried law-mismatch part, against the achieved reported "
            "half-width: {:.0%} of {} cells within 30%.",
        ),
    ]
    for k, (key, errs, sentence) in enumerate(shares):
        if k == 0 or errs:
            within = float(np.mean(np.abs(np.asarray(errs) - 1) <= 0.3))
            summary[key] = within
            lines.append(sentence.format(within, len(errs)))
            summary[key + "_count"] = [int(np.sum(np.abs(np.asarray(errs) - 1) <= 0.3)), len(errs)]
    lines += [""] + shift_table(results, summary)
    return "\n".join(lines), summary


def shift_table(results, summary) -> list[str]:
    """The mismatch mean's predicted shift of the pooled estimate per round against the
    estimate's change that round (the designed rows that recorded it)."""
    lines = [
        "**The drag predicted against the estimate's change** (rounds 1-3: the pooled "
        "estimate's shift predicted before the round from the mismatch mean measured so far, "
        "`Designer.drag_of`, against values after the round minus before; medians over "
        "repeats, each relative to the estimate; the sign's agreement over repeats).",
        "",
        "| case | parameter | episodes | predicted shift | achieved change | same sign |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    agree = []
    for case, res in results.items():
        rows = [r for r in res["rows"] if r["signal"] == "designed" and "predicted_shift" in r]
        if not rows:
            continue
        for i, label in enumerate(res["labels"]):
            for j, n in enumerate(np.cumsum(ROUNDS)):
                if j == 0:
                    continue
                pred = [r["predicted_shift"][j][i] / r["values"][j - 1][i] for r in rows]
                got = [
                    (r["values"][j][i] - r["values"][j - 1][i]) / r["values"][j - 1][i]
                    for r in rows
                ]
                same = [np.sign(a) == np.sign(b) for a, b in zip(pred, got, strict=True)]
                agree += same
                lines.append(
                    f"| {case} | {label} | {n} | {np.median(pred):.3g} | {np.median(got):.3g} "
                    f"| {sum(same)}/{len(same)} |"
                )
    if agree:
        summary["drag_sign_agrees"] = [int(sum(agree)), len(agree)]
        lines.append("")
        lines.append(f"Same sign in {sum(agree)} of {len(agree)} (case, parameter, round, repeat).")
    return lines


def figure(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(results)
    fig, axes = plt.subplots(2, n, figsize=(4.5 * n, 7.0), squeeze=False)
    for row, (key, what) in enumerate((("ratio", "noise part"), ("ratio_reported", "reported"))):
        for ax, (case, res) in zip(axes[row], results.items(), strict=True):
            for s in SIGNALS:
                rows = [r for r in res["rows"] if r["signal"] == s]
                sec = np.array(rows[0]["seconds"])
                rat = np.array([r[key] for r in rows])
                (line,) = ax.plot(sec, np.median(rat, axis=0), marker="o", label=s)
                ax.fill_between(sec, rat.min(0), rat.max(0), color=line.get_color(), alpha=0.15)
            ax.axhline(1.0, color="k", lw=0.8, ls="--")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("plant seconds")
            ax.set_ylabel(f"half-width / target ({what})")
            ax.set_title(case)
            ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", default=",".join(c for c in CASES if c != "furuta"))
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument(
        "--criterion",
        default="asked",
        help="the design's criterion: asked (the case's widths {parameter: relative "
        "half-width}, weighted A-optimal), D (determinant) or A (trace)",
    )
    ap.add_argument(
        "--parameterisation",
        default="per_step",
        choices=["per_step", "fourier"],
        help="the designed arm's parameterisation (hds.discover.design.Designer.design)",
    )
    ap.add_argument(
        "--iterations",
        default="200,100",
        help="the designed arm's Adam iterations: round 0, then each later round",
    )
    ap.add_argument(
        "--signals",
        default=",".join(SIGNALS),
        help="the signals to run; the case's stored rows of the others are kept (results.json)",
    )
    ap.add_argument(
        "--mismatch",
        default="none",
        choices=["calibrated", "raw", "none"],
        help="the law mismatch the designed arm's criterion holds from round 1 on: the model "
        "measured so far (Designer.mismatch) calibrated to the fit's noise part, uncalibrated, "
        "or none (sensor noise alone: the default, the better on the measurement, README); "
        "the predictions with the mismatch model are recorded for every choice",
    )
    ap.add_argument(
        "--drag",
        default="off",
        choices=["off", "on"],
        help="on: the designed arm's criterion (from round 1) is the mean squared error with "
        "the drag of the law mismatch's mean measured so far (Designer.mismatch_mean); the "
        "drag's predictions are recorded either way",
    )
    ap.add_argument(
        "--repeat-from",
        type=int,
        default=0,
        help="run repeats from this one on (their noise seeds as in a whole run), keeping the "
        "stored rows of the earlier repeats: a long case in pieces on a loaded machine",
    )
    ap.add_argument("--out", default=str(HERE))
    ap.add_argument("--report", action="store_true", help="only rewrite the tables and figure")
    args = ap.parse_args()
    # the Furuta's design step overflows the stack of an XLA compile thread (README, Furuta)
    # unless XLA's fusion emitters are off; the flag must be set before JAX starts its backend
    flag = "--xla_cpu_use_fusion_emitters=false"
    if "furuta" in args.cases.split(",") and flag not in os.environ.get("XLA_FLAGS", ""):
        raise SystemExit(
            f"the furuta case needs XLA_FLAGS={flag} (its design's compile crashes XLA "
            f"otherwise): XLA_FLAGS={flag} python -m experiments.excitation_design --cases furuta"
        )
    logging.basicConfig(level=logging.WARNING)
    enable_compilation_cache()
    out = Path(args.out)
    start = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - start:7.1f} s] {msg}", flush=True)

    stored = {}
    if args.report:
        stored = json.loads((out / "results.json").read_text())
        results = stored["cases"]
    else:
        # each case is written as it ends, beside the cases of earlier runs into `out`
        # (run the cases apart, e.g. on a loaded machine); --report tabulates them all
        done = out / "results.json"
        results = json.loads(done.read_text())["cases"] if done.is_file() else {}
        signals = tuple(args.signals.split(","))
        iterations = tuple(int(x) for x in args.iterations.split(","))
        if not set(signals) <= set(SIGNALS) or len(iterations) != 2:
            raise SystemExit(
                f"--signals {args.signals!r} must name some of {list(SIGNALS)} and --iterations "
                f"{args.iterations!r} two numbers (round 0, later rounds)"
            )
        for c in args.cases.split(","):
            new = run_case(
                c,
                CASES[c],
                args.repeats,
                log,
                args.criterion,
                args.parameterisation,
                iterations,
                signals,
                args.mismatch,
                args.repeat_from,
                args.drag,
            )
            if c in results and (set(signals) != set(SIGNALS) or args.repeat_from):
                # keep the other signals' rows and these signals' earlier repeats
                kept = [
                    r
                    for r in results[c]["rows"]
                    if r["signal"] not in signals or r["repeat"] < args.repeat_from
                ]
                new["rows"] = kept + new["rows"]
            results[c] = new
            results[c]["criterion"] = args.criterion
            atomic_write_json(done, {"cases": results})
    table, summary = summarise(results)
    meta = stored.get("meta") or {
        "date": time.strftime("%Y-%m-%d"),
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "wall_s": time.perf_counter() - start,
        "repeats": args.repeats,
        "rounds": list(ROUNDS),
        "amplitude": AMPLITUDE,
    }
    atomic_write_json(out / "results.json", {"meta": meta, "summary": summary, "cases": results})
    atomic_write_bytes(out / "results.md", (table + "\n").encode())
    figure(results, out / "width_vs_time.png")
    print(table)
    print(
        json.dumps({k: v for k, v in summary.items() if k != "predicted_over_achieved"}, indent=1)
    )
    log("done")


if __name__ == "__main__":
    main()
