"""The System that hds's own backends (analytic, tree) read, built from MuJoCo's compiled model
without brax.

The own backends read a few fields of brax's System (links, dofs, actuators, gravity, the
timestep; `hds.envs.tree`'s docstring lists them) and the effects edit some of them. Building
brax's System for that imported brax, whose import brings mujoco.mjx with scipy.spatial and
trimesh, and ran `brax.io.mjcf.load_model`, whose copies into jax arrays each compiled a small
program: ~1 s of a process from an empty compilation cache (bench/RESULTS.md, section
"compile"). `system_of` builds the same fields, the same values as float32 and int32 jax
arrays (what load_model gives them), under the same names, from the MjModel in numpy: a
program traced on it is the one traced on brax's System, op for op. Models outside the own
backends' reach (free, ball or several joints on a body) get brax's System as before, so that
the backends' checks refuse them with the same words.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from hds.utils.pytree import pytree_dataclass, static_field

_HINGE, _SLIDE = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)


@pytree_dataclass
class Transform:
    pos: jax.Array
    rot: jax.Array


@pytree_dataclass
class Inertia:
    transform: Transform
    i: jax.Array
    mass: jax.Array


@pytree_dataclass
class Link:
    transform: Transform
    joint: Transform
    inertia: Inertia
    invweight: jax.Array


@pytree_dataclass
class Motion:
    ang: jax.Array
    vel: jax.Array


@pytree_dataclass
class DoF:
    motion: Motion
    armature: jax.Array
    stiffness: jax.Array
    damping: jax.Array
    limit: tuple | None
    invweight: jax.Array
    solver_params: jax.Array


@pytree_dataclass
class Actuator:
    q_id: jax.Array
    qd_id: jax.Array
    ctrl_range: jax.Array
    force_range: jax.Array
    gain: jax.Array
    gear: jax.Array
    bias_q: jax.Array
    bias_qd: jax.Array


@pytree_dataclass
class Option:
    timestep: jax.Array


@pytree_dataclass
class System:
    """brax's System as the own backends and the effects read it: brax's field names, and
    MuJoCo's own fields that the effects edit beside them (body_mass, ...), as brax's System
    carries them for the mjx backend."""

    gravity: jax.Array
    opt: Option
    link: Link
    dof: DoF
    actuator: Actuator
    body_mass: jax.Array
    body_inertia: jax.Array
    body_ipos: jax.Array
    dof_damping: jax.Array
    dof_invweight0: jax.Array
    actuator_gear: jax.Array
    link_names: list = static_field()
    link_types: str = static_field()
    link_parents: tuple = static_field()
    nq: int = static_field()
    nv: int = static_field()
    nu: int = static_field()
    mj_model: mujoco.MjModel = static_field(default=None)

    def num_links(self) -> int:
        return len(self.link_types)

    def q_size(self) -> int:
        return self.nq

    def qd_size(self) -> int:
        return self.nv

    def act_size(self) -> int:
        return self.nu


def supported(model: mujoco.MjModel) -> bool:
    """Whether every body but the world carries exactly one hinge or slide joint (the trees
    the own backends can simulate, and the structure `system_of` builds)."""
    types = np.asarray(model.jnt_type)
    bodies = np.asarray(model.jnt_bodyid)
    return (
        model.nbody > 1
        and model.njnt == model.nbody - 1
        and np.array_equal(bodies, np.arange(1, model.nbody))
        and bool(np.all((types == _HINGE) | (types == _SLIDE)))
    )


def _arrays(tree):
    """Each numpy leaf as the jax array load_model makes of it (`jnp.array`: float64 to float32,
    int64 to int32), without its copy, which compiled a program per shape."""

    def put(x):
        x = np.asarray(x)
        return jax.device_put(x.astype(jax.dtypes.canonicalize_dtype(x.dtype)))

    return jax.tree.map(put, tree)


def system_of(model: mujoco.MjModel) -> System:
    """The System of a `supported` model: what `brax.io.mjcf.load_model` computes for these
    fields, to the last digit (tests/test_mjsystem.py compares them). `model` is not edited."""
    if not supported(model):
        raise ValueError("system_of takes trees of one hinge or slide joint per body")
    m, body = model, slice(1, None)  # brax's links skip the world body
    hinge = (np.asarray(m.jnt_type) == _HINGE)[:, None]
    axis = np.asarray(m.jnt_axis)
    limited = np.asarray(m.jnt_limited) == 1
    lo = np.where(limited, m.jnt_range[:, 0], -np.inf)
    hi = np.where(limited, m.jnt_range[:, 1], np.inf)
    # one dof per joint: the dof's joint is the joint itself
    solver_params = np.concatenate((m.jnt_solref, m.jnt_solimp), axis=1)[m.dof_jntid]
    unlimited = np.array([-np.inf, np.inf])
    ctrl_range = np.where((m.actuator_ctrllimited == 1)[:, None], m.actuator_ctrlrange, unlimited)
    force_range = np.where(
        (m.actuator_forcelimited == 1)[:, None], m.actuator_forcerange, unlimited
    )
    biased = m.actuator_biastype != 0
    joint = m.actuator_trntype == mujoco.mjtTrn.mjTRN_JOINT  # brax's actuators: joint ones
    trnid = m.actuator_trnid[joint, 0].astype(np.uint32)
    identity = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (m.nbody - 1, 1))
    arrays = _arrays(
        {
            "gravity": m.opt.gravity,
            "timestep": np.float64(m.opt.timestep),
            "link": Link(
                transform=Transform(pos=m.body_pos[body], rot=m.body_quat[body]),
                joint=Transform(pos=m.jnt_pos, rot=identity),
                inertia=Inertia(
                    transform=Transform(pos=m.body_ipos[body], rot=m.body_iquat[body]),
                    i=np.array([np.diag(i) for i in m.body_inertia[body]]),
                    mass=m.body_mass[body],
                ),
                invweight=m.body_invweight0[body, 0],
            ),
            "dof": DoF(
                motion=Motion(ang=np.where(hinge, axis, 0.0), vel=np.where(hinge, 0.0, axis)),
                armature=m.dof_armature,
                stiffness=m.jnt_stiffness,
                damping=m.dof_damping,
                limit=(lo, hi) if np.any(m.jnt_limited) else None,
                invweight=m.dof_invweight0,
                solver_params=solver_params,
            ),
            "actuator": Actuator(
                q_id=m.jnt_qposadr[trnid],
                qd_id=m.jnt_dofadr[trnid],
                ctrl_range=ctrl_range[joint],
                force_range=force_range[joint],
                gain=m.actuator_gainprm[joint, 0],
                gear=m.actuator_gear[joint, 0],
                bias_q=(m.actuator_biasprm[:, 1] * biased)[joint],
                bias_qd=(m.actuator_biasprm[:, 2] * biased)[joint],
            ),
            "mujoco": {
                k: getattr(m, k)
                for k in (
                    "body_mass",
                    "body_inertia",
                    "body_ipos",
                    "dof_damping",
                    "dof_invweight0",
                    "actuator_gear",
                )
            },
        }
    )
    return System(
        gravity=arrays["gravity"],
        opt=Option(timestep=arrays["timestep"]),
        link=arrays["link"],
        dof=arrays["dof"],
        actuator=arrays["actuator"],
        **arrays["mujoco"],
        link_names=[m.body(i).name for i in range(1, m.nbody)],
        link_types="1" * (m.nbody - 1),
        link_parents=tuple(m.body_parentid - 1)[1:],
        nq=int(m.nq),
        nv=int(m.nv),
        nu=int(m.nu),
        mj_model=model,
    )


def to_tau(sys, act: jax.Array, q: jax.Array, qd: jax.Array) -> jax.Array:
    """Joint forces of actuator inputs `act`: `brax.actuator.to_tau`, op for op (gear, gain,
    bias, ctrl and force clipping), on brax's System or this module's."""
    if sys.act_size() == 0:
        return jnp.zeros(sys.qd_size())
    ctrl_range, force_range = sys.actuator.ctrl_range, sys.actuator.force_range
    q, qd = q[sys.actuator.q_id], qd[sys.actuator.qd_id]
    act = jnp.clip(act, ctrl_range[:, 0], ctrl_range[:, 1])
    # brax uses the gear for the bias term too (mujoco/discussions/754)
    bias = sys.actuator.gear * (q * sys.actuator.bias_q + qd * sys.actuator.bias_qd)
    force = sys.actuator.gain * act + bias
    force = jnp.clip(force, force_range[:, 0], force_range[:, 1])
    force *= sys.actuator.gear
    return jnp.zeros(sys.qd_size()).at[sys.actuator.qd_id].add(force)
