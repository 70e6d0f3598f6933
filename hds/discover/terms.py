"""Beyond the library: sparse symbolic force terms fitted to what the named effects leave.

The one-step velocity residual of a window (measured minus predicted) is what the generalized
force the simulator misses does over a step; through C MuJoCo's response to a force held over
the step, at the window's measured state (`missing_force`), it is that force, in N (slide) or
N m (hinge).
Per joint, that force is regressed on candidate terms of the window's state and action, by
forward selection on the held-out episodes' error (a term is added while it lowers the held-out
mean squared force error by at least `stop_margin` of it and MIN_SHARE of the joint's missing
force), the way discovery selects effects. Each term is reported with units and a physical
reading (a force -k q on a rail is a spring), and a joint's terms are added to the corrected
model as one `joint_force_terms` effect (`term_effects`).

Terms: the features of hds.effects.force_terms (q, sin q and cos q, qd, sign(qd), |qd| qd)
and each action. A hinge's angle has two readings (`angle_reading`): periodic, where only sin q
and cos q are offered (a torque the same a turn later), or unwrapped, where its own angle q, as
the plant integrates it, is offered beside them (a torsional spring -k q: a cable, a spring
return, a flexure). The unwrapped reading is taken unless the record wraps the angle (it jumps
by about a turn between two samples, so q is not the integrated angle); which reading each hinge
took, and what in the data showed it, is reported (`Reading`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import mujoco
import numpy as np

from hds.discover.compare import Residuals
from hds.discover.data import Data
from hds.effects.force_terms import FEATURE, FEATURES, HINGE, SLIDE
from hds.envs.system import load_spec

TURN = 2.0 * np.pi
MIN_SHARE = 0.01  # a term must explain this share of a joint's missing-force variance
TERM_EFFECT = "joint_force_terms"

log = logging.getLogger("hds")


@dataclass
class Term:
    joint: str
    term: str  # as reports write it (actions: "u <name>")
    coefficient: float
    unit: str
    reading: str
    share: float  # of the joint's missing-force variance on held-out episodes it explains
    param: str  # the coefficient's parameter of the joint_force_terms effect
    actuator: int  # for a term in a control: the actuator's index (else 0)

    def to_json(self) -> dict:
        return dict(self.__dict__)

    def describe(self) -> str:
        return (
            f"a force on {self.joint} of {self.coefficient:.4g} x {self.term} "
            f"({self.unit}): {self.reading}; {self.share:.0%} of the missing force"
        )


@dataclass
class Reading:
    """How a hinge's angle was read by the term fit: `unwrapped` (its own angle q offered) or
    periodic (sin q and cos q only), and the evidence in the data."""

    joint: str
    unwrapped: bool
    why: str
    span_turns: float  # how many turns the record's angles span
    chosen: bool = False  # a term in q was selected on this joint

    def to_json(self) -> dict:
        return dict(self.__dict__)

    def describe(self) -> str:
        if not self.unwrapped:
            return f"{self.joint}: periodic reading (sin q, cos q only): {self.why}"
        taken = "a term in q was selected" if self.chosen else "no term in q was selected"
        return f"{self.joint}: unwrapped angle q offered ({taken}): {self.why}"


def angle_reading(model: mujoco.MjModel, j: int, q: np.ndarray, q_next: np.ndarray) -> Reading:
    """The reading of hinge j's angle from the record's angles q at window starts and q_next
    one sample later. A jump of more than half a turn in one sample is the record wrapping the
    angle (no hinge of a sampled plant turns that fast): q is then not the angle the plant
    integrates, and a torque in it would be a step at the wrap, so only the periodic terms
    are offered. Otherwise q is the plant's own integrated angle and is offered: a limited
    joint never completes a turn, a record spanning more than a turn shows the angle
    unwrapped, and within one turn without a limit the data cannot tell the readings apart
    at the seam, so held-out error chooses between q and sin q, cos q."""
    name = model.joint(j).name
    span = float(np.ptp(np.r_[q, q_next]) / TURN) if len(q) else 0.0
    jumps = int(np.sum(np.abs(q_next - q) > 0.5 * TURN))
    if jumps:
        why = (
            f"the record wraps the angle ({jumps} jumps of about a turn between samples): "
            "it is not the angle the plant integrates"
        )
        return Reading(name, False, why, span)
    lo, hi = (float(x) for x in model.jnt_range[j])
    if model.jnt_limited[j] and hi - lo < TURN:
        why = f"the joint is limited to [{lo:.3g}, {hi:.3g}] rad, less than a turn"
    elif span > 1.0:
        why = f"its angles span {span:.2f} turns, unwrapped as the plant integrates them"
    else:
        why = (
            f"its angles stay within one turn ({span:.2f}) and never wrap: held-out error "
            "chooses between q and the periodic terms"
        )
    return Reading(name, True, why, span)


def term_effects(terms: list[Term]) -> list[dict]:
    """The terms as effects: one `joint_force_terms` per joint (a joint's terms in one control
    only: a term in a second actuator's control is left out, with a warning)."""
    by_joint: dict[str, dict] = {}
    for t in terms:
        effect = by_joint.setdefault(
            t.joint, {"name": TERM_EFFECT, "target": t.joint, "params": {}}
        )
        params = effect["params"]
        if t.param == "u" and "u" in params:
            log.warning("%s: not added (a joint's terms use one control)", t.describe())
            continue
        params[t.param] = t.coefficient
        if t.param == "u":
            params["actuator"] = t.actuator
    return list(by_joint.values())


def with_terms(effects: list[dict], terms: list[Term]) -> list[dict]:
    """`effects` plus the terms' effects; terms on a joint that already has a
    `joint_force_terms` effect add to its coefficients."""
    out = [dict(e, params=dict(e["params"])) for e in effects]
    placed = {(e["name"], e["target"]): e for e in out}
    for new in term_effects(terms):
        old = placed.get((TERM_EFFECT, new["target"]))
        if old is None:
            out.append(new)
            continue
        for param, value in new["params"].items():
            known = 0.0 if param == "actuator" else old["params"].get(param, 0.0)
            old["params"][param] = known + value
    return out


def _velocity_after(model: mujoco.MjModel, mj: mujoco.MjData, x, force, frames: int):
    """The velocity after `frames` steps of C MuJoCo's nominal model from state x, with no
    control and the generalized force `force` held."""
    mujoco.mj_resetData(model, mj)
    mj.qpos[:], mj.qvel[:] = x[: model.nq], x[model.nq :]
    mj.qfrc_applied[:] = force
    mujoco.mj_step(model, mj, nstep=frames)
    return mj.qvel.copy()


def missing_force(res: Residuals, data: Data, model: mujoco.MjModel) -> np.ndarray:
    """[W, nv] generalized force the simulator misses at each window's start: the force that,
    held over the step in C MuJoCo's nominal model, changes the velocity by the one-step
    residual. The response to a force is measured per window (one step per dof, a unit force
    each), not read as M^-1 h: MuJoCo's Euler treats damping implicitly, h (M + h D)^-1, and
    a step of several frames lets the damping and the coupled dofs act on what the force has
    already changed (a cart-pole's hinge spring read through M alone comes out 6% weak)."""
    obs = np.asarray(data.obs, dtype=np.float64)[res.episode, res.start]
    frames = max(round(data.dt / model.opt.timestep), 1)
    mj = mujoco.MjData(model)
    unit = np.eye(model.nv)
    out = np.empty((len(obs), model.nv))
    for w, (x, dv) in enumerate(zip(obs, res.one_step[:, model.nq :], strict=True)):
        base = _velocity_after(model, mj, x, unit[0] * 0.0, frames)
        response = np.stack(
            [_velocity_after(model, mj, x, unit[d], frames) - base for d in range(model.nv)], 1
        )
        out[w] = np.linalg.lstsq(response, dv, rcond=None)[0]
    return out


def compensations(named, terms: list[Term]) -> list[str]:
    """Warnings for named effects (NamedEffect) that a term of the same law on the same joint
    largely cancels: the named effect compensated for what the other terms now explain (a
    viscous damping standing in for quadratic drag); the corrected model carries their sum."""
    out = []
    for t in terms:
        law = FEATURE[t.param].same_law
        for e in named:
            if law is None or (e.name, e.target) != (law[0], t.joint):
                continue
            value = e.params[law[1]]
            net = value - t.coefficient  # the named force is -value x term
            if abs(net) < 0.5 * abs(value):
                others = ", ".join(o.term for o in terms if o.joint == t.joint and o is not t)
                out.append(
                    f"{e.name}@{e.target} ({law[1]} = {value:.4g} {e.units[law[1]]}) and the "
                    f"term {t.coefficient:.4g} x {t.term} nearly cancel (net {net:.4g}): the "
                    f"named effect compensated for {others or 'the other terms'}; the "
                    "corrected model carries their sum"
                )
    return out


def joint_type(model: mujoco.MjModel, j: int) -> str:
    return HINGE if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE else SLIDE


def features(
    res: Residuals, data: Data, model: mujoco.MjModel, j: int, unwrapped: bool = True
) -> dict[str, np.ndarray]:
    """{term: value at each window's start} of joint j: its FEATURES and each action (on a
    hinge read as periodic, `unwrapped` False, not its own angle q)."""
    obs = np.asarray(data.obs, dtype=np.float64)[res.episode, res.start]
    pad = data.acts.shape[1] - (data.obs.shape[1] - 1)
    acts = np.asarray(data.acts, dtype=np.float64)[res.episode, pad + res.start]
    q, qd = obs[:, j], obs[:, model.nq + j]
    kind = joint_type(model, j)
    out = {
        f.label: f.value(np, q, qd, np.sign(qd), None)
        for f in FEATURES
        if kind in f.joints and f.param != "u" and (f.param != "q" or kind != HINGE or unwrapped)
    }
    for a, name in enumerate(data.action_names):
        out[f"u {name}"] = FEATURE["u"].value(np, q, qd, None, acts[:, a])
    return out


def select(
    x_fit, y_fit, x_held, y_held, names, stop_margin: float, weight: float = 1.0
) -> list[tuple[str, float, float]]:
    """Forward selection of columns (with an intercept) on held-out error: (name, coefficient,
    share of the held-out variance the term added when it entered). `weight`: the joint's
    share of the whole one-step residual; a term must explain MIN_SHARE of that whole, not
    only of its joint's own force (a joint the simulator predicts to a rounding error has
    structure too, in what its neighbours' missing force leaves behind over a step)."""
    chosen: list[int] = []
    base = float(np.mean((y_held - y_held.mean()) ** 2))
    errors = [base]
    coef = np.zeros(0)
    while len(chosen) < len(names) and base > 0:
        trials = {}
        for c in range(len(names)):
            if c in chosen:
                continue
            cols = chosen + [c]
            a = np.c_[np.ones(len(y_fit)), x_fit[:, cols]]
            w, *_ = np.linalg.lstsq(a, y_fit, rcond=None)
            pred = np.c_[np.ones(len(y_held)), x_held[:, cols]] @ w
            trials[c] = (float(np.mean((y_held - pred) ** 2)), w[1:])
        best = min(trials, key=lambda c: trials[c][0])
        drop = errors[-1] - trials[best][0]
        if not (drop >= stop_margin * errors[-1] and drop * weight >= MIN_SHARE * base):
            break
        chosen.append(best)
        errors.append(trials[best][0])
        coef = trials[best][1]
    shares = [(errors[i] - errors[i + 1]) / base for i in range(len(chosen))]
    return [(names[c], float(w), s) for c, w, s in zip(chosen, coef, shares, strict=True)]


def readings(model: mujoco.MjModel, data: Data, sets: list[Residuals]) -> dict[str, Reading]:
    """{hinge: its angle's Reading} from the windows of `sets` (their first two samples)."""
    obs = np.asarray(data.obs, dtype=np.float64)
    episode = np.concatenate([r.episode for r in sets])
    start = np.concatenate([r.start for r in sets])
    return {
        model.joint(j).name: angle_reading(
            model, j, obs[episode, start, j], obs[episode, start + 1, j]
        )
        for j in range(model.njnt)
        if joint_type(model, j) == HINGE
    }


def fit_terms(
    env_cfg, data: Data, ident: Residuals, held: Residuals, stop_margin: float
) -> tuple[list[Term], list[Reading]]:
    """The sparse terms of each joint's missing force (see the module's docstring), and how
    each hinge's angle was read."""
    model = load_spec(env_cfg.xml, env_cfg.timestep).compile()
    f_fit, f_held = missing_force(ident, data, model), missing_force(held, data, model)
    label = {f.label: f for f in FEATURES}
    angles = readings(model, data, [ident, held])
    # each dof's share of the held-out one-step velocity residual, in units of each
    # velocity's spread (discovery's normalized error)
    scale = np.asarray(data.scale, dtype=np.float64)[model.nq :]
    spread = np.mean((held.one_step[:, model.nq :] / scale) ** 2, axis=0)
    weights = spread / max(float(spread.sum()), 1e-300)
    out = []
    for j in range(model.njnt):
        joint, kind = model.joint(j).name, joint_type(model, j)
        unwrapped = angles[joint].unwrapped if joint in angles else True
        feats_fit = features(ident, data, model, j, unwrapped)
        feats_held = features(held, data, model, j, unwrapped)
        names = list(feats_fit)
        x_fit = np.stack([feats_fit[n] for n in names], 1)
        x_held = np.stack([feats_held[n] for n in names], 1)
        dof = int(model.jnt_dofadr[j])
        picked = select(
            x_fit, f_fit[:, dof], x_held, f_held[:, dof], names, stop_margin, weights[dof]
        )
        for name, coef, share in picked:
            control = name.startswith("u ")
            feature = FEATURE["u"] if control else label[name]
            actuator = data.action_names.index(name[2:]) if control else 0
            unit = feature.unit_on(kind)
            out.append(
                Term(joint, name, coef, unit, feature.reading, share, feature.param, actuator)
            )
            if joint in angles and feature.param == "q":
                angles[joint].chosen = True
    return out, list(angles.values())
