"""Beyond the library: sparse symbolic force terms fitted to what the named effects leave.

The one-step velocity residual of a window (measured minus predicted) is the generalized
acceleration the simulator misses times dt; times the mass matrix M(q) (C MuJoCo's, at the
window's measured state) it is the missing generalized force, in N (slide) or N m (hinge).
Per joint, that force is regressed on candidate terms of the window's state and action, by
forward selection on the held-out episodes' error (a term is added while it lowers the held-out
mean squared force error by at least `stop_margin` of it and MIN_SHARE of the joint's missing
force), the way discovery selects effects. Reported, not yet added to the corrected model.
Each term is reported with units and a physical reading: a force -k q on a rail is a spring.

Terms: q (slide) or sin q, cos q (hinge); qd; sign(qd); |qd| qd; each action.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from hds.discover.compare import Residuals
from hds.discover.data import Data
from hds.envs.system import load_spec

MIN_SHARE = 0.01  # a term must explain this share of a joint's missing-force variance

READINGS = {  # term -> (unit of its coefficient, physical reading of a force -c * term)
    "q": ("{F}/{Q}", "a spring (stiffness k = -coefficient)"),
    "sin q": ("{F}", "a torque in sin of the angle (gravity-like)"),
    "cos q": ("{F}", "a torque in cos of the angle (an offset gravity)"),
    "qd": ("{F} s/{Q}", "viscous friction (coefficient = -coefficient)"),
    "sign(qd)": ("{F}", "dry (Coulomb) friction (force = -coefficient)"),
    "|qd| qd": ("{F} s^2/{Q}^2", "quadratic drag (coefficient = -coefficient)"),
    "u": ("{F} per control unit", "a force proportional to the control"),
}


@dataclass
class Term:
    joint: str
    term: str  # one of READINGS' keys (actions: "u <name>")
    coefficient: float
    unit: str
    reading: str
    share: float  # of the joint's missing-force variance on held-out episodes it explains

    def to_json(self) -> dict:
        return dict(self.__dict__)

    def describe(self) -> str:
        return (
            f"a force on {self.joint} of {self.coefficient:.4g} x {self.term} "
            f"({self.unit}): {self.reading}; {self.share:.0%} of the missing force"
        )


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


def features(res: Residuals, data: Data, model: mujoco.MjModel, j: int) -> dict[str, np.ndarray]:
    obs = np.asarray(data.obs, dtype=np.float64)[res.episode, res.start]
    pad = data.acts.shape[1] - (data.obs.shape[1] - 1)
    acts = np.asarray(data.acts, dtype=np.float64)[res.episode, pad + res.start]
    q, qd = obs[:, j], obs[:, model.nq + j]
    out = {}
    if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE:
        out["sin q"], out["cos q"] = np.sin(q), np.cos(q)
    else:
        out["q"] = q
    out["qd"], out["sign(qd)"], out["|qd| qd"] = qd, np.sign(qd), np.abs(qd) * qd
    for a, name in enumerate(data.action_names):
        out[f"u {name}"] = acts[:, a]
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
    out = []
    for j in range(model.njnt):
        joint = model.joint(j).name
        hinge = model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
        units = {"F": "N m" if hinge else "N", "Q": "rad" if hinge else "m"}
        feats_fit, feats_held = features(ident, data, model, j), features(held, data, model, j)
        names = list(feats_fit)
        x_fit = np.stack([feats_fit[n] for n in names], 1)
        x_held = np.stack([feats_held[n] for n in names], 1)
        dof = int(model.jnt_dofadr[j])
        picked = select(x_fit, f_fit[:, dof], x_held, f_held[:, dof], names, stop_margin)
        for name, coef, share in picked:
            unit, reading = READINGS[name.split(" ")[0] if name.startswith("u ") else name]
            out.append(Term(joint, name, coef, unit.format(**units), reading, share))
    return out
