"""A closed-form physics backend for the two structures the project ships: cart-pole and pendulum.

It has the functional interface of brax's pipelines (`init(sys, q, qd)`, `step(sys, state, act)`,
a `State` with `q` and `qd`), so `make_simulator(..., backend="analytic")` uses it like
`brax.generalized.pipeline`. Each step is a few dozen scalar operations instead of brax's
general tree algorithms: on a 2-core CPU, a 100-step, batch-64 gradient rollout of the
cart-pole compiles in about 4 CPU-seconds (generalized: about 40) and runs about 100 times as
many env steps per second (about 0.7M against 7k, forward and backward).

Supported models (checked once, by `check(sys)`, when the simulator is built):
  (a) a slide joint on a body whose parent is the world, carrying one child body with a hinge
      (a cart-pole), with q = [slide, hinge];
  (b) a single hinge on a body whose parent is the world (a pendulum), with q = [hinge].
Any other model raises a ValueError that names backend=generalized as the way out.

What it models, read from the System (brax's fields, hds.envs.mjsystem) on every step (so
effects that edit the System, mass_scale on `link.inertia` and actuator_gain on
`actuator.gear`, act on it):
  - rigid-body dynamics from the Lagrangian of the structure: masses (`link.inertia.mass`),
    centre-of-mass offsets and inertia tensors with their principal frames (`link.inertia`),
    body frames (`link.transform`), hinge anchors (`link.joint.pos`), joint axes of any
    direction (`dof.motion`), gravity of any direction (`gravity`);
  - joint armature (added to the mass matrix), joint damping, joint stiffness with spring
    reference 0 (as brax does);
  - actuators as `brax.actuator.to_tau` (hds.envs.mjsystem.to_tau: gear, gain, bias, ctrl and
    force clipping; the unlimited force motors through which effect forces enter);
  - joint limits as MuJoCo's soft constraints: the same reference acceleration from the
    joint's solref/solimp (`dof.solver_params`), the same regulariser from `dof.invweight`,
    and MuJoCo's `refsafe` rule (time constant at least twice the timestep). With one limit
    active this is the exact solution of MuJoCo's constraint problem; two limits active at
    once (only possible when the hinge is limited too) are solved one joint at a time;
  - MuJoCo's Euler integrator: the acceleration with joint damping treated implicitly,
    (M + h D) qdd = forces, then qd += h qdd, then q += h qd with the new qd.

What it does not model (it ignores them silently, as brax's generalized backend does, or
`check` refuses the model where ignoring would be wrong):
  - contacts and collisions: a model whose geoms can collide, or with contact pairs, is refused;
  - joint frictionloss (dry friction), actuator dynamics (filters, delay): ignored, as in brax
    generalized (use the project's effects to model them);
  - tendons, equality constraints, fluid forces (viscosity, density): refused;
  - integrators other than Euler: refused (brax's backends refuse them too);
  - spring reference positions other than 0 (springref), MuJoCo's `eulerdamp` disable flag,
    limit margins: ignored.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from hds.envs.mjsystem import to_tau
from hds.utils.pytree import pytree_dataclass

_SUPPORTED = (
    "the analytic backend supports a slide joint carrying a hinge, and a single hinge; "
    "use backend=generalized for this model"
)
_MINVAL = 1e-15  # MuJoCo's mjMINVAL
_MINIMP, _MAXIMP = 0.0001, 0.9999  # MuJoCo's clamp of constraint impedance


@pytree_dataclass
class State:
    """Joint positions and velocities, and the acceleration of the last step."""

    q: jax.Array
    qd: jax.Array
    qdd: jax.Array


def _structure(sys) -> str:
    """'cartpole' or 'pendulum'; raises ValueError for anything else."""
    types = str(sys.link_types)
    parents = tuple(int(p) for p in sys.link_parents)
    ang = np.asarray(sys.dof.motion.ang)
    vel = np.asarray(sys.dof.motion.vel)
    is_hinge = [bool(np.any(a != 0) and not np.any(v != 0)) for a, v in zip(ang, vel)]
    is_slide = [bool(np.any(v != 0) and not np.any(a != 0)) for a, v in zip(ang, vel)]
    if len(sys.link_names) == len(types):  # every body has exactly its own joint group
        if types == "11" and parents == (-1, 0) and is_slide == [True, False] and is_hinge[1]:
            return "cartpole"
        if types == "1" and parents == (-1,) and is_hinge == [True]:
            return "pendulum"
    joints = ["slide" if s else "hinge" if h else "other" for s, h in zip(is_slide, is_hinge)]
    raise ValueError(
        f"{_SUPPORTED} (this model has bodies {list(sys.link_names)} with parents "
        f"{list(parents)}, joint groups '{types}' and joints {joints})"
    )


def _may_collide(mj) -> bool:
    """Whether contacts can arise: explicit pairs, or two geoms on different bodies whose
    contype/conaffinity match, less MuJoCo's parent-child filter and <exclude> pairs."""
    if mj.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_CONTACT:
        return False
    if mj.npair > 0:
        return True
    filter_parent = not mj.opt.disableflags & mujoco.mjtDisableBit.mjDSBL_FILTERPARENT
    # <exclude body1 body2>: MuJoCo stores each as (body1 << 16) + body2
    excluded = {frozenset((int(sig) >> 16, int(sig) & 0xFFFF)) for sig in mj.exclude_signature}
    body, ctype, caff = mj.geom_bodyid, mj.geom_contype, mj.geom_conaffinity
    for i in range(mj.ngeom):
        for j in range(i + 1, mj.ngeom):
            a, b = int(body[i]), int(body[j])
            if a == b or frozenset((a, b)) in excluded:
                continue
            parent_child = mj.body_parentid[a] == b or mj.body_parentid[b] == a
            if filter_parent and parent_child and min(a, b) != 0:
                continue
            if (ctype[i] & caff[j]) or (ctype[j] & caff[i]):
                return True
    return False


def check(sys) -> str:
    """Check once, when the simulator is built, that this backend can simulate `sys`.

    Returns the structure ('cartpole' or 'pendulum'); raises ValueError otherwise."""
    structure = _structure(sys)
    check_options(sys, "analytic", _SUPPORTED)
    return structure


def check_options(sys, backend: str, supported: str) -> None:
    """Refuse what a smooth-dynamics backend does not model: another integrator, contacts,
    tendons, equality constraints, fluid forces. `supported` starts the message."""
    mj = getattr(sys, "mj_model", None)
    if mj is None:
        return
    if int(mj.opt.integrator) != 0:
        raise ValueError(
            f"the {backend} backend integrates like MuJoCo's Euler integrator, as brax's "
            "backends do: set <option integrator='Euler'/> in the MJCF"
        )
    problems = []
    if _may_collide(mj):
        problems.append("geoms that can collide (contacts are not modelled)")
    if mj.ntendon > 0:
        problems.append("tendons")
    if mj.neq > 0:
        problems.append("equality constraints")
    if mj.opt.viscosity > 0 or mj.opt.density > 0:
        problems.append("fluid forces (viscosity or density)")
    if problems:
        raise ValueError(f"{supported}: it has {', '.join(problems)}")


def init(sys, q: jax.Array, qd: jax.Array, *args, **kwargs) -> State:
    """The physics state at (q, qd); extra arguments (brax's act, ctrl, debug) are ignored."""
    del args, kwargs
    q, qd = jnp.asarray(q), jnp.asarray(qd)
    return State(q=q, qd=qd, qdd=jnp.zeros_like(qd))


def quat_matrix(quat, xp):
    """Rotation matrix of a quaternion (w, x, y, z), in numpy or jax.numpy."""
    w, x, y, z = quat / xp.linalg.norm(quat)
    return xp.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def system_geometry(sys) -> tuple[dict, object]:
    """The System's frames, axes and gravity (effects never edit them) and the array module
    for them: numpy float64 when known at trace time, else the traced arrays and jax.numpy."""
    parts = {
        "rot": sys.link.transform.rot,
        "pos": sys.link.transform.pos,
        "irot": sys.link.inertia.transform.rot,
        "ipos": sys.link.inertia.transform.pos,
        "jpos": sys.link.joint.pos,
        "ang": sys.dof.motion.ang,
        "vel": sys.dof.motion.vel,
        "gravity": sys.gravity,
    }
    values = concrete(list(parts.values()))
    if values is None:
        return parts, jnp
    return dict(zip(parts, values)), np


def _geometry(sys) -> dict:
    """The mass-independent terms of the dynamics, from the System's frames and axes.

    With h the hinge's link and d(theta) the world-frame offset of its COM from the hinge
    anchor, d_perp = P cos + W sin (the part normal to the axis) and dd/dtheta = W cos - P sin.
    Returns the dot products of P and W with gravity and the slide axis, |d_perp|^2, and the
    hinge axis in the link's principal inertia frame. Computed in numpy when the geometry is
    known at trace time (effects never edit it), so a step carries only the terms that vary."""
    parts, xp = system_geometry(sys)
    rot, ipos, irot, jpos = parts["rot"], parts["ipos"], parts["irot"], parts["jpos"]
    ang, vel, gravity = parts["ang"], parts["vel"], parts["gravity"]
    h = sys.num_links() - 1  # the hinge's link (and dof): the last of one or two
    frame = quat_matrix(rot[h], xp)  # the hinge link's frame at hinge = 0, in world
    slide = xp.zeros(3)
    if h == 1:  # cart-pole: the pole's frame hangs from the cart's
        frame = quat_matrix(rot[0], xp) @ frame
        slide = quat_matrix(rot[0], xp) @ (vel[0] / xp.linalg.norm(vel[0]))
    axis = ang[h] / xp.linalg.norm(ang[h])
    v = ipos[h] - jpos[h]
    v_perp = v - axis * xp.dot(axis, v)
    p, w = frame @ v_perp, frame @ xp.cross(axis, v)
    terms = {
        "gp": xp.dot(gravity, p),
        "gw": xp.dot(gravity, w),
        "sp": xp.dot(slide, p),
        "sw": xp.dot(slide, w),
        "gs": xp.dot(gravity, slide),
        "rho2": xp.dot(v_perp, v_perp),
        "axis_i": quat_matrix(irot[h], xp).T @ axis,
    }
    if xp is np:
        terms = {k: np.asarray(x, dtype=np.float32) for k, x in terms.items()}
    return terms


def _dynamics(sys, q: jax.Array, qd: jax.Array):
    """Mass matrix M (armature included) and the smooth forces except actuators and damping."""
    geo = _geometry(sys)
    h = sys.num_links() - 1
    mass = sys.link.inertia.mass
    e = geo["axis_i"]
    i_hinge = e @ sys.link.inertia.i[h] @ e + mass[h] * geo["rho2"]  # about the hinge axis
    c, s = jnp.cos(q[h]), jnp.sin(q[h])
    gravity_hinge = mass[h] * (geo["gw"] * c - geo["gp"] * s)
    if h == 0:  # pendulum
        return jnp.reshape(i_hinge + sys.dof.armature[0], (1, 1)), jnp.reshape(gravity_hinge, (1,))
    # cart-pole: q = [x, theta]; the cart translates along the slide, the pole turns about the hinge
    m_total = mass[0] + mass[1]
    m12 = mass[1] * (geo["sw"] * c - geo["sp"] * s)
    mat = jnp.array([[m_total + sys.dof.armature[0], m12], [m12, i_hinge + sys.dof.armature[1]]])
    centrifugal = mass[1] * (geo["sp"] * c + geo["sw"] * s) * qd[1] ** 2
    return mat, jnp.stack([centrifugal + m_total * geo["gs"], gravity_hinge])


def _inverse(mass: jax.Array) -> jax.Array:
    """Closed-form inverse of a 1x1 or 2x2 symmetric matrix."""
    if mass.shape[0] == 1:
        return 1.0 / mass
    a, b, d = mass[0, 0], mass[0, 1], mass[1, 1]
    return jnp.array([[d, -b], [-b, a]]) / (a * d - b * b)


def concrete(arrays):
    """The arrays in numpy (float64) when known at trace time, else None (a traced System)."""
    try:
        return [np.asarray(a, dtype=np.float64) for a in arrays]
    except jax.errors.TracerArrayConversionError:
        return None


def _limit_constants(sys, h):
    """The limited dofs and their q-independent soft-limit terms (MuJoCo's solref/solimp).

    Returns (dofs, terms): dofs a numpy index array (every dof when the System is traced).
    The terms are numpy when the System is known at trace time, so a step carries none of this."""
    n = sys.dof.damping.shape[0]
    if sys.dof.limit is None:
        return np.zeros(0, dtype=np.int32), {}
    parts = (*sys.dof.limit, sys.dof.solver_params, sys.dof.invweight, h)
    values = concrete(parts)
    xp = jnp if values is None else np
    lo, hi, params, invweight, h = parts if values is None else values
    if values is None:
        dofs = np.arange(n)
    else:
        dofs = np.flatnonzero(np.isfinite(lo) | np.isfinite(hi))
    lo, hi, params, invweight = lo[dofs], hi[dofs], params[dofs], invweight[dofs]
    timeconst, dampratio, dmin, dmax, width, mid, power = params.T
    dmin, dmax = xp.clip(dmin, _MINIMP, _MAXIMP), xp.clip(dmax, _MINIMP, _MAXIMP)
    mid, power = xp.clip(mid, _MINIMP, _MAXIMP), xp.maximum(power, 1.0)
    # solref: (timeconst, dampratio), or, when <= 0, (-stiffness, -damping); MuJoCo's refsafe
    # rule keeps the time constant at least twice the timestep
    standard = timeconst > 0
    tc = xp.where(standard, xp.maximum(timeconst, 2 * h), 1.0)
    ratio = xp.where(standard, dampratio, 1.0)
    terms = {
        "lo": xp.where(xp.isfinite(lo), lo, -1e10),
        "hi": xp.where(xp.isfinite(hi), hi, 1e10),
        "b": xp.where(standard, 2 / (dmax * tc), -dampratio / dmax),
        "k": xp.where(standard, 1 / (dmax * dmax * tc * tc * ratio * ratio), -timeconst / dmax**2),
        "dmin": dmin,
        "dmax": dmax,
        "width": xp.maximum(width, _MINVAL),
        "mid": mid,
        "power": power,
        "scale_lo": 1 / mid ** (power - 1),
        "scale_hi": 1 / (1 - mid) ** (power - 1),
        "invweight": invweight,
    }
    if values is not None:
        terms = {key: np.asarray(x, dtype=np.float32) for key, x in terms.items()}
    return dofs.astype(np.int32), terms


def take(x: jax.Array, dofs: np.ndarray) -> jax.Array:
    """x[dofs], as a static slice when the dofs are contiguous (no gather under vmap and grad)."""
    first = int(dofs[0])
    if np.array_equal(dofs, np.arange(first, first + dofs.size)):
        return x[first : first + dofs.size]
    return x[dofs]


def put(values: jax.Array, dofs: np.ndarray, n: int) -> jax.Array:
    """A length-n vector with `values` at `dofs` and zeros elsewhere."""
    first = int(dofs[0])
    if np.array_equal(dofs, np.arange(first, first + dofs.size)):
        return jnp.pad(values, (first, n - first - dofs.size))
    return jnp.zeros(n, values.dtype).at[dofs].set(values)


def limit_terms(sys, q, qd, h):
    """MuJoCo's soft joint-limit terms at (q, qd): the limited dofs (numpy indices) and, per
    limited dof, whether it is active, the side it pushes (+1: the lower limit pushes up), the
    reference acceleration and the regulariser. None when the model has no limits."""
    dofs, c = _limit_constants(sys, h)
    if dofs.size == 0:
        return None
    q, qd = take(q, dofs), take(qd, dofs)
    dist_lo, dist_hi = q - c["lo"], c["hi"] - q
    side = jnp.where(dist_lo < dist_hi, 1.0, -1.0)
    dist = jnp.minimum(dist_lo, dist_hi)
    active = dist < 0
    pos = jnp.where(active, dist, 0.0)
    # impedance (solimp); a safe input where inactive keeps gradients finite
    x = jnp.clip(jnp.where(active, -pos / c["width"], c["mid"]), 0.0, 1.0)
    lower = x < c["mid"]
    z = jnp.where(lower, x, 1 - x)
    power = c["power"]
    if isinstance(power, np.ndarray) and np.all(power == power[0]) and power[0] == int(power[0]):
        zp = z ** int(power[0])  # the usual integer power (2): multiplications
    else:
        zp = jnp.power(z, power)
    y = jnp.where(lower, zp * c["scale_lo"], 1 - zp * c["scale_hi"])  # 1 at x = 1
    imp = c["dmin"] + y * (c["dmax"] - c["dmin"])
    aref = -c["b"] * side * qd - c["k"] * imp * pos
    reg = jnp.maximum(_MINVAL, (1 - imp) / imp * c["invweight"])
    return dofs, active, side, aref, reg


def _limit_force(sys, q, qd, acc_free, mass_inv, h):
    """MuJoCo's soft joint-limit force, per joint, given the unconstrained acceleration."""
    terms = limit_terms(sys, q, qd, h)
    if terms is None:
        return jnp.zeros_like(q)
    dofs, active, side, aref, reg = terms
    a = take(jnp.diagonal(mass_inv), dofs)
    force = jnp.maximum(0.0, (aref - side * take(acc_free, dofs)) / (a + reg))
    return put(jnp.where(active, side * force, 0.0), dofs, q.shape[0])


def step(sys, state: State, act: jax.Array, *args, **kwargs) -> State:
    """One MuJoCo-style Euler step of `sys.opt.timestep` under actuator inputs `act`.

    Rematerialised, as the tree engine's step: reverse mode recomputes the step from its
    inputs instead of keeping its intermediates for every step of a rollout, and XLA compiles
    the trainer's program in less time (bench/RESULTS.md, section "compile")."""
    del args, kwargs
    return jax.checkpoint(lambda s, a: _euler_step(sys, s, a))(state, act)


def _euler_step(sys, state: State, act: jax.Array) -> State:
    h = sys.opt.timestep
    q, qd = state.q, state.qd
    mass, bias = _dynamics(sys, q, qd)
    damping = sys.dof.damping
    force = to_tau(sys, act, q, qd) + bias - damping * qd - sys.dof.stiffness * q
    mass_inv = _inverse(mass)
    force = force + _limit_force(sys, q, qd, mass_inv @ force, mass_inv, h)
    qdd = _inverse(mass + jnp.diag(h * damping)) @ force  # damping implicit, as MuJoCo's Euler
    qd = qd + h * qdd
    return State(q=q + h * qd, qd=qd, qdd=qdd)
