"""How much of a lab draw's rigid-body and motor error a named model leaves: the measure of
what discovery's inertial scales and motor gain predict, where the scales one by one do not.

A lab draw changes every body's mass, centre of mass and inertia and the motor's gain. The
motion shows a few combinations of them (a pendulum's gravity torque over its inertia about
the pivot, the motor's gain over the arm's inertia), so discovery's named scales trade off:
on Furuta draw 4 the loop named the arm's inertia 2.8 times the nominal where the truth's is
1.10 (and its gain 0.91, its mass 1.10), and predicts the arm within 8% of the nominal's
error. This measure compares what the models predict: per joint, the acceleration MuJoCo's
forward dynamics give (without contacts, limits, friction, damping or springs) over sampled
states and controls, as the RMS difference from the truth's, relative to the nominal
model's: 0 where the named model predicts what the truth does, 1 where it does no better
than naming nothing. Effects outside the rigid body and the motor's gain (friction, delays,
a belt's backlash, which adds the motor's inertia to the cart's) do not enter.

States: each joint's position uniform over its range (a free hinge over a turn), its speed
uniform within +-SPEED (per joint type), each control uniform over its range; seeded.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import mujoco
import numpy as np

from hds.real.mujoco_plant import mujoco_spec

# the effects of the rigid body and the motor (each a scale, no effect at 1)
RIGID = ("mass_scale", "com_scale", "inertia_scale", "actuator_gain")
HINGE, SLIDE = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)
SPEED = {HINGE: 2 * math.pi, SLIDE: 1.0}  # rad/s, m/s: a swing a second, a metre a second
SAMPLES = 1024


def rigid_effects(effects: list[dict]) -> list[dict]:
    """The rigid-body and motor effects of a list (a truth's or discovery's named ones)."""
    return [e for e in effects if e["name"] in RIGID]


def _model(xml: str, effects: list[dict]) -> mujoco.MjModel:
    model = mujoco_spec(SimpleNamespace(xml=xml, timestep=None), effects).compile()
    off = mujoco.mjtDisableBit
    for flag in (off.mjDSBL_CONSTRAINT, off.mjDSBL_DAMPER, off.mjDSBL_SPRING):
        model.opt.disableflags |= flag
    return model


def states(model: mujoco.MjModel, n: int = SAMPLES, seed: int = 0):
    """(q [n, nq], qd [n, nv], u [n, nu]) sampled as the module says (slide and hinge joints:
    one position and one speed each)."""
    rng = np.random.default_rng(seed)
    kinds = model.jnt_type
    if not np.isin(kinds, (HINGE, SLIDE)).all() or model.nq != model.nv:
        raise ValueError("the rigid-body measure takes models of slide and hinge joints only")
    low = np.where(model.jnt_limited, model.jnt_range[:, 0], -math.pi)
    high = np.where(model.jnt_limited, model.jnt_range[:, 1], math.pi)
    speed = np.array([SPEED[int(k)] for k in kinds])
    limited = model.actuator_ctrllimited.astype(bool)[:, None]
    ctrl = np.where(limited, model.actuator_ctrlrange, [-1.0, 1.0])
    q = rng.uniform(low, high, (n, model.nq))
    qd = rng.uniform(-speed, speed, (n, model.nv))
    u = rng.uniform(ctrl[:, 0], ctrl[:, 1], (n, model.nu))
    return q, qd, u


def accelerations(model: mujoco.MjModel, q, qd, u) -> np.ndarray:
    """[n, nv] the joints' accelerations the model predicts in each state under each control."""
    data = mujoco.MjData(model)
    out = np.empty((len(q), model.nv))
    for i in range(len(q)):
        data.qpos[:], data.qvel[:], data.ctrl[:] = q[i], qd[i], u[i]
        mujoco.mj_forward(model, data)
        out[i] = data.qacc
    return out


def error_left(xml: str, truth: list[dict], named: list[dict], n: int = SAMPLES, seed: int = 0):
    """{joint: RMS(named - truth) / RMS(nominal - truth)} of the acceleration each model
    predicts, over the sampled states and controls; only the rigid-body and motor effects of
    `truth` and `named` count (0: the truth's dynamics; 1: the nominal's error)."""
    nominal = _model(xml, [])
    q, qd, u = states(nominal, n, seed)
    true = accelerations(_model(xml, rigid_effects(truth)), q, qd, u)
    fit = accelerations(_model(xml, rigid_effects(named)), q, qd, u)
    base = accelerations(nominal, q, qd, u)
    rms = lambda x: np.sqrt(np.mean(x**2, axis=0))  # noqa: E731
    left = rms(fit - true) / rms(base - true)
    names = [nominal.joint(int(nominal.dof_jntid[d])).name for d in range(nominal.nv)]
    return dict(zip(names, map(float, left), strict=True))
