"""Beyond the library: sparse symbolic force terms fitted to what the named effects leave.

The one-step velocity residual of a window (measured minus predicted) is the generalized
acceleration the simulator misses times dt; times the mass matrix M(q) (C MuJoCo's, at the
window's measured state) it is the missing generalized force, in N (slide) or N m (hinge).
Per joint, that force is regressed on candidate terms of the window's state and action, by
forward selection on the held-out episodes' error (a term is added while it lowers the held-out
mean squared force error by at least `stop_margin` of it and MIN_SHARE of the joint's missing
force), the way discovery selects effects. Each term is reported with units and a physical
reading (a force -k q on a rail is a spring), and a joint's terms are added to the corrected
model as one `joint_force_terms` effect (`term_effects`).

Terms: the features of hds.effects.force_terms (q on a slide, sin q and cos q on a hinge, qd,
sign(qd), |qd| qd) and each action.
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


def missing_force(res: Residuals, data: Data, model: mujoco.MjModel) -> np.ndarray:
    """[W, nv] generalized force the simulator misses at each window's start."""
    obs = np.asarray(data.obs, dtype=np.float64)[res.episode, res.start]
    nq = model.nq
    mj = mujoco.MjData(model)
    full = np.zeros((model.nv, model.nv))
    out = np.empty((len(obs), model.nv))
    for w, (x, dv) in enumerate(zip(obs, res.one_step[:, nq:], strict=True)):
        mj.qpos[:] = x[:nq]
        mujoco.mj_fwdPosition(model, mj)
        mujoco.mj_fullM(model, mj, full)
        out[w] = full @ (dv / data.dt)
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


def features(res: Residuals, data: Data, model: mujoco.MjModel, j: int) -> dict[str, np.ndarray]:
    """{term: value at each window's start} of joint j: its FEATURES and each action."""
    obs = np.asarray(data.obs, dtype=np.float64)[res.episode, res.start]
    pad = data.acts.shape[1] - (data.obs.shape[1] - 1)
    acts = np.asarray(data.acts, dtype=np.float64)[res.episode, pad + res.start]
    q, qd = obs[:, j], obs[:, model.nq + j]
    kind = joint_type(model, j)
    out = {
        f.label: f.value(np, q, qd, np.sign(qd), None)
        for f in FEATURES
        if kind in f.joints and f.param != "u"
    }
    for a, name in enumerate(data.action_names):
        out[f"u {name}"] = FEATURE["u"].value(np, q, qd, None, acts[:, a])
    return out


def select(
    x_fit, y_fit, x_held, y_held, names, stop_margin: float
) -> list[tuple[str, float, float]]:
    """Forward selection of columns (with an intercept) on held-out error: (name, coefficient,
    share of the held-out variance the term added when it entered)."""
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
        if not (drop >= stop_margin * errors[-1] and drop >= MIN_SHARE * base):
            break
        chosen.append(best)
        errors.append(trials[best][0])
        coef = trials[best][1]
    shares = [(errors[i] - errors[i + 1]) / base for i in range(len(chosen))]
    return [(names[c], float(w), s) for c, w, s in zip(chosen, coef, shares, strict=True)]


def fit_terms(env_cfg, data: Data, ident: Residuals, held: Residuals, stop_margin: float):
    """The sparse terms of each joint's missing force (see the module's docstring)."""
    model = load_spec(env_cfg.xml, env_cfg.timestep).compile()
    f_fit, f_held = missing_force(ident, data, model), missing_force(held, data, model)
    label = {f.label: f for f in FEATURES}
    out = []
    for j in range(model.njnt):
        joint, kind = model.joint(j).name, joint_type(model, j)
        feats_fit, feats_held = features(ident, data, model, j), features(held, data, model, j)
        names = list(feats_fit)
        x_fit = np.stack([feats_fit[n] for n in names], 1)
        x_held = np.stack([feats_held[n] for n in names], 1)
        dof = int(model.jnt_dofadr[j])
        picked = select(x_fit, f_fit[:, dof], x_held, f_held[:, dof], names, stop_margin)
        for name, coef, share in picked:
            control = name.startswith("u ")
            feature = FEATURE["u"] if control else label[name]
            actuator = data.action_names.index(name[2:]) if control else 0
            unit = feature.unit_on(kind)
            out.append(
                Term(joint, name, coef, unit, feature.reading, share, feature.param, actuator)
            )
    return out
