"""A physics backend for any kinematic tree of hinge and slide joints, without contacts.

It has the functional interface of brax's pipelines (`init`, `step`, a `State` with `q` and
`qd`), like `hds.envs.analytic`, whose closed forms it generalises: `make_simulator(...,
backend="tree")`. The tree's structure (parents, joint types) is static, so a step unrolls
over the bodies at trace time: up to three dofs into scalar operations, with everything that
depends only on the geometry folded while tracing (a cart-pole step is then about as cheap as
`analytic`'s closed form); larger trees into operations on [bodies, ...] arrays.

Supported models (checked once, by `check(sys)`): every body has exactly one hinge or slide
joint; no contacts, tendons, equality constraints or fluid forces; MuJoCo's Euler integrator.
Anything else raises a ValueError that names the backend to use instead.

What it models, read from the brax System on every step (so effects that edit the System,
mass_scale on `link.inertia` and actuator_gain on `actuator.gear`, act on it):
  - rigid-body dynamics in world coordinates (spatial vectors about the world origin): the
    composite-rigid-body mass matrix and recursive Newton-Euler bias forces (Coriolis,
    centrifugal, gravity), from masses, COM offsets, inertia tensors and their principal
    frames, body frames, joint anchors and axes of any direction, gravity of any direction;
  - joint armature, damping (implicit, as MuJoCo's Euler), stiffness with spring reference 0;
  - actuators through `brax.actuator.to_tau` (gear, gain, bias, ctrl and force clipping; the
    unlimited motors through which effect forces enter);
  - joint limits as MuJoCo's soft constraints (`analytic.limit_terms`: solref/solimp, refsafe,
    invweight regulariser), several active limits solved together as MuJoCo's constraint
    solver does (`_limit_force`);
  - MuJoCo's Euler integrator: (M + h D) qdd = forces, qd += h qdd, q += h qd.
Ignored, as in `analytic`: joint frictionloss, actuator dynamics, springref, joint ref,
limit margins (the project's effects model friction and actuator dynamics).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from brax import actuator

from hds.envs.analytic import (
    State,
    check_options,
    concrete,
    init,
    limit_terms,
    put,
    quat_matrix,
    system_geometry,
)

__all__ = ["State", "check", "init", "step"]

_SUPPORTED = (
    "the tree backend supports trees of hinge and slide joints, one per body, without "
    "contacts, tendons or equality constraints"
)


def check(sys) -> None:
    """Refuse, once when the simulator is built, what this backend cannot simulate."""
    types = str(sys.link_types)
    if len(sys.link_names) != len(types) or set(types) - {"1"}:
        joints = "free" if "f" in types else "ball or multi-joint"
        raise ValueError(
            f"{_SUPPORTED}: this model has {joints} bodies (joint groups '{types}' on bodies "
            f"{list(sys.link_names)}); use backend=generalized for it"
        )
    ang, vel = np.asarray(sys.dof.motion.ang), np.asarray(sys.dof.motion.vel)
    for name, a, v in zip(sys.link_names, ang, vel, strict=True):
        if np.any(a != 0) == np.any(v != 0):
            raise ValueError(
                f"{_SUPPORTED}: body '{name}' has a joint that is neither; "
                "use backend=generalized for it"
            )
    mj = getattr(sys, "mj_model", None)
    if mj is not None and (mj.ntendon > 0 or mj.neq > 0):
        raise ValueError(
            f"{_SUPPORTED}: it has tendons or equality constraints; use backend=mjx for it"
        )
    check_options(sys, "tree", f"{_SUPPORTED}; use backend=generalized for this model")


# -- scalar algebra ---------------------------------------------------------------------------
# A step is written over scalars, not arrays: under vmap each is a [batch] vector and XLA fuses
# the whole step into a few elementwise loops (small dots and gathers would each be a kernel
# of their own, whose launch costs more than its arithmetic). Quantities known at trace time
# (the geometry, and the masses when no effect edits them) are Python floats, so products of
# constants fold while tracing and exact zeros (axis-aligned frames, no damping) emit nothing.


def _is(x, value: float) -> bool:
    return isinstance(x, float) and x == value


def _mul(a, b):
    if _is(a, 0.0) or _is(b, 0.0):
        return 0.0
    if _is(a, 1.0):
        return b
    return a if _is(b, 1.0) else a * b


def _add(a, b):
    if _is(a, 0.0):
        return b
    return a if _is(b, 0.0) else a + b


def _sub(a, b):
    if _is(b, 0.0):
        return a
    return -b if _is(a, 0.0) else a - b


def _sum(terms):
    return functools.reduce(_add, terms, 0.0)


def _dot(u, v):
    return _sum(_mul(a, b) for a, b in zip(u, v, strict=True))


def _vadd(u, v):
    return tuple(map(_add, u, v))


def _vsub(u, v):
    return tuple(map(_sub, u, v))


def _scale(s, v):
    return tuple(_mul(s, x) for x in v)


def _cross(u, v):
    return (
        _sub(_mul(u[1], v[2]), _mul(u[2], v[1])),
        _sub(_mul(u[2], v[0]), _mul(u[0], v[2])),
        _sub(_mul(u[0], v[1]), _mul(u[1], v[0])),
    )


def _matvec(m, v):
    return tuple(_dot(row, v) for row in m)


def _matmul(a, b):
    columns = tuple(zip(*b, strict=True))
    return tuple(tuple(_dot(row, col) for col in columns) for row in a)


def _values(x):
    """Nested tuples of Python floats when x is known at trace time, else of traced scalars."""
    known = concrete([x])
    if known is not None:
        return _tuples(known[0].tolist())
    return _tuples(x)


def _tuples(x):
    if isinstance(x, float) or not jnp.ndim(x):
        return x
    return tuple(_tuples(e) for e in x)


# -- the model --------------------------------------------------------------------------------


def _geometry(sys) -> list[dict]:
    """Per body, its frame and joint relative to its parent (effects never edit them)."""
    parts, xp = system_geometry(sys)
    bodies = []
    for i, parent in enumerate(int(p) for p in sys.link_parents):
        hinge = bool(np.any(np.asarray(sys.dof.motion.ang)[i] != 0))
        axis = parts["ang"][i] if hinge else parts["vel"][i]
        axis = axis / xp.linalg.norm(axis)
        turn = xp.cross(xp.eye(3), axis)  # [axis]x: a hinge turns by I + sin K + (1 - cos) K^2
        body = {
            "rot": quat_matrix(parts["rot"][i], xp),
            "pos": parts["pos"][i],
            "irot": quat_matrix(parts["irot"][i], xp),
            "ipos": parts["ipos"][i],
            "jpos": parts["jpos"][i],
            "axis": axis,
            "k": turn,
            "k2": turn @ turn,
        }
        bodies.append({k: _values(v) for k, v in body.items()} | {"parent": parent, "hinge": hinge})
    return bodies


def _kinematics(bodies, q):
    """World frames at q, body by body down the tree: per body its rotation, centre of mass
    and joint motion subspace (angular, linear about the world origin)."""
    frames, origins, coms, subspaces = [], [], [], []
    for i, b in enumerate(bodies):
        if b["parent"] < 0:
            frame, origin = b["rot"], b["pos"]
        else:
            parent = frames[b["parent"]]
            frame = _matmul(parent, b["rot"])
            origin = _vadd(origins[b["parent"]], _matvec(parent, b["pos"]))
        axis = _matvec(frame, b["axis"])
        if b["hinge"]:  # rotate about the anchor, which stays put
            anchor = _vadd(origin, _matvec(frame, b["jpos"]))
            sin, vers = jnp.sin(q[i]), 1.0 - jnp.cos(q[i])
            turned = _matmul(frame, b["k"]), _matmul(frame, b["k2"])
            frame = tuple(
                tuple(_add(f, _add(_mul(sin, k), _mul(vers, k2))) for f, k, k2 in zip(*rows))
                for rows in zip(frame, *turned)
            )
            origin = _vsub(anchor, _matvec(frame, b["jpos"]))
            subspaces.append((axis, _cross(anchor, axis)))
        else:
            origin = _vadd(origin, _scale(q[i], axis))
            subspaces.append(((0.0, 0.0, 0.0), axis))
        frames.append(frame)
        origins.append(origin)
        coms.append(_vadd(origin, _matvec(frame, b["ipos"])))
    return frames, coms, subspaces


def _inertias(sys, bodies, frames, coms):
    """Per body, its spatial inertia about the world origin as (mass, first moment m c,
    rotational inertia about the origin J = I_com - m [c]x[c]x), in world axes."""
    masses, tensors = _values(sys.link.inertia.mass), _values(sys.link.inertia.i)
    out = []
    for b, frame, com, mass, tensor in zip(bodies, frames, coms, masses, tensors, strict=True):
        principal = _matmul(frame, b["irot"])
        rotated = _matmul(_matmul(principal, tensor), tuple(zip(*principal)))
        moment = _scale(mass, com)
        square = _dot(moment, com)
        inertia = tuple(
            tuple(
                _add(rotated[r][k], _sub(square if r == k else 0.0, _mul(moment[r], com[k])))
                for k in range(3)
            )
            for r in range(3)
        )
        out.append((mass, moment, inertia))
    return out


def _apply(inertia, motion):
    """Spatial inertia times a motion (angular w, linear v at the origin): the momentum."""
    mass, moment, rotational = inertia
    w, v = motion
    return (
        _vadd(_matvec(rotational, w), _cross(moment, v)),
        _vsub(_scale(mass, v), _cross(moment, w)),
    )


def _cross_motion(v, m):
    return _cross(v[0], m[0]), _vadd(_cross(v[0], m[1]), _cross(v[1], m[0]))


def _cross_force(v, f):
    return _vadd(_cross(v[0], f[0]), _cross(v[1], f[1])), _cross(v[0], f[1])


def _add6(a, b):
    return _vadd(a[0], b[0]), _vadd(a[1], b[1])


def _dot6(a, b):
    return _add(_dot(a[0], b[0]), _dot(a[1], b[1]))


def _ancestors(parents) -> list[list[int]]:
    """Per body, itself and its ancestors."""
    chains = []
    for i, parent in enumerate(parents):
        chains.append([i, *(chains[parent] if parent >= 0 else [])])
    return chains


def _unrolled_dynamics(sys, q, qd):
    """Mass matrix M (armature included; nested tuples) and the bias forces (Coriolis,
    centrifugal, gravity): composite rigid bodies and recursive Newton-Euler with qdd = 0 and
    gravity as an upward acceleration of the world."""
    bodies = _geometry(sys)
    parents = [b["parent"] for b in bodies]
    n = len(bodies)
    frames, coms, s = _kinematics(bodies, q)
    inertias = _inertias(sys, bodies, frames, coms)
    zero = (0.0, 0.0, 0.0)
    gravity = _values(sys.gravity)
    vel, acc, force = [], [], []
    for i, parent in enumerate(parents):
        joint = (_scale(qd[i], s[i][0]), _scale(qd[i], s[i][1]))
        v_parent = vel[parent] if parent >= 0 else (zero, zero)
        a_parent = acc[parent] if parent >= 0 else (zero, _scale(-1.0, gravity))
        vel.append(_add6(v_parent, joint))
        acc.append(_add6(a_parent, _cross_motion(vel[i], joint)))
        momentum = _apply(inertias[i], vel[i])
        force.append(_add6(_apply(inertias[i], acc[i]), _cross_force(vel[i], momentum)))
    composite = list(inertias)
    for i in reversed(range(n)):  # sums up the tree: children come after their parents
        if parents[i] >= 0:
            p = parents[i]
            force[p] = _add6(force[p], force[i])
            (m, h, j), (mc, hc, jc) = composite[p], composite[i]
            composite[p] = (_add(m, mc), _vadd(h, hc), tuple(map(_vadd, j, jc)))
    bias = tuple(_dot6(s[i], force[i]) for i in range(n))
    armature = _values(sys.dof.armature)
    mass = [[0.0] * n for _ in range(n)]
    for k, chain in enumerate(_ancestors(parents)):
        column = _apply(composite[k], s[k])
        for j in chain:
            mass[j][k] = mass[k][j] = _dot6(s[j], column)
        mass[k][k] = _add(mass[k][k], armature[k])
    return mass, bias


# -- larger trees: stacked over the bodies ------------------------------------------------


def _stacked_constants(sys) -> dict:
    """The geometry (effects never edit it): numpy when known at trace time, else traced."""
    parts, xp = system_geometry(sys)
    rot, pos, irot, ipos = parts["rot"], parts["pos"], parts["irot"], parts["ipos"]
    jpos, ang, vel, gravity = parts["jpos"], parts["ang"], parts["vel"], parts["gravity"]
    n = len(sys.link_names)
    hinge = [bool(np.any(np.asarray(a) != 0)) for a in np.asarray(sys.dof.motion.ang)]
    axis = xp.where(xp.asarray(hinge)[:, None], ang, vel)
    axis = axis / xp.linalg.norm(axis, axis=1, keepdims=True)
    cross = [xp.cross(xp.eye(3), axis[i]) for i in range(n)]  # [k]x, the axis' cross matrix
    return {
        "above": _tree_matrix(sys.link_parents),
        "hinge": hinge,
        "rot": [quat_matrix(rot[i], xp) for i in range(n)],
        "pos": pos,
        "irot": xp.stack([quat_matrix(irot[i], xp) for i in range(n)]),
        "ipos": ipos,
        "jpos": jpos,
        "axis": axis,
        "k": cross,
        "k2": [c @ c for c in cross],
        "gravity": gravity,
    }


def _tree_matrix(parents) -> np.ndarray:
    """[n, n] with 1 where j is i's ancestor or i itself (static: it shapes the unrolled step)."""
    n = len(parents)
    above = np.zeros((n, n), dtype=np.float32)
    for i in range(n):
        j = i
        while j >= 0:
            above[i, j] = 1.0
            j = parents[j]
    return above


# Products of small matrices as broadcast multiplies and sums: under vmap a matmul becomes a
# batched dot, a kernel of its own per product, which costs more than its arithmetic.
def _mm(a, b):
    """a @ b over the last two axes."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _mv(a, v):
    """a @ v, a [..., m, k], v [..., k]."""
    return jnp.sum(a * v[..., None, :], axis=-1)


def _down(above, x):
    """above @ x for the static [n, n] ancestor matrix and x [n, 6]."""
    return jnp.sum(above[:, :, None] * x[None], axis=1)


def _skew(v):
    """[..., 3] -> [..., 3, 3] cross-product matrices."""
    zero = jnp.zeros_like(v[..., 0])
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    rows = [
        jnp.stack([zero, -z, y], -1),
        jnp.stack([z, zero, -x], -1),
        jnp.stack([-y, x, zero], -1),
    ]
    return jnp.stack(rows, -2)


def _cross_motion_rows(v, m):
    """Spatial motion cross products v x m, row by row; [n, 6] (angular, linear at the origin)."""
    w, u = v[:, :3], v[:, 3:]
    return jnp.concatenate(
        [jnp.cross(w, m[:, :3]), jnp.cross(w, m[:, 3:]) + jnp.cross(u, m[:, :3])], axis=1
    )


def _cross_force_rows(v, f):
    """Spatial force cross products v x* f, row by row."""
    w, u = v[:, :3], v[:, 3:]
    return jnp.concatenate(
        [jnp.cross(w, f[:, :3]) + jnp.cross(u, f[:, 3:]), jnp.cross(w, f[:, 3:])], axis=1
    )


def _stacked_kinematics(sys, g, q):
    """World frames of the bodies at q, body by body down the tree: rotations [n, 3, 3],
    centres of mass [n, 3] and joint motion subspaces [n, 6] about the world origin."""
    rots, origins, coms, subspaces = [], [], [], []
    for i, parent in enumerate(sys.link_parents):
        if parent < 0:
            frame, origin = jnp.asarray(g["rot"][i]), jnp.asarray(g["pos"][i])
        else:
            frame = _mm(rots[parent], g["rot"][i])
            origin = origins[parent] + _mv(rots[parent], g["pos"][i])
        axis = _mv(frame, g["axis"][i])
        if g["hinge"][i]:  # rotate about the anchor, which stays put
            anchor = origin + _mv(frame, g["jpos"][i])
            turn = jnp.sin(q[i]) * g["k"][i] + (1 - jnp.cos(q[i])) * g["k2"][i]
            frame = frame + _mm(frame, turn)
            origin = anchor - _mv(frame, g["jpos"][i])
            subspaces.append(jnp.concatenate([axis, jnp.cross(anchor, axis)]))
        else:
            origin = origin + axis * q[i]
            subspaces.append(jnp.concatenate([jnp.zeros(3), axis]))
        rots.append(frame)
        origins.append(origin)
        coms.append(origin + _mv(frame, g["ipos"][i]))
    return jnp.stack(rots), jnp.stack(coms), jnp.stack(subspaces)


def _spatial_inertias(sys, g, rots, coms):
    """[n, 6, 6] inertias about the world origin, in world axes."""
    mass = sys.link.inertia.mass
    principal = _mm(rots, g["irot"])
    inertia = _mm(_mm(principal, sys.link.inertia.i), jnp.swapaxes(principal, 1, 2))
    c = _skew(coms)
    m = mass[:, None, None]
    top = jnp.concatenate([inertia + m * _mm(jnp.swapaxes(c, 1, 2), c), m * c], axis=2)
    bottom = jnp.concatenate([m * jnp.swapaxes(c, 1, 2), m * jnp.eye(3)], axis=2)
    return jnp.concatenate([top, bottom], axis=1)


def _stacked_dynamics(sys, q, qd):
    """Mass matrix M (armature included) and the bias forces (Coriolis, centrifugal, gravity).

    Vectorised over the bodies with the static ancestor matrix: velocities and velocity-product
    accelerations sum down the tree, forces sum up it (recursive Newton-Euler with qdd = 0 and
    gravity as an upward acceleration of the world); M[j, k] = sum over bodies i below both
    j and k of s_j . I_i s_k (composite rigid bodies)."""
    g = _stacked_constants(sys)
    above = g["above"]
    rots, coms, s = _stacked_kinematics(sys, g, q)
    inertia = _spatial_inertias(sys, g, rots, coms)
    joint = s * qd[:, None]
    vel = _down(above, joint)
    base = jnp.concatenate([jnp.zeros(3), -jnp.asarray(g["gravity"], q.dtype)])
    acc = base + _down(above, _cross_motion_rows(vel, joint))
    momentum = _mv(inertia, vel)
    force = _mv(inertia, acc) + _cross_force_rows(vel, momentum)
    bias = jnp.sum(s * _down(above.T, force), axis=1)
    sis = jnp.sum(s[None, :, None] * _mv(inertia[:, None], s[None])[:, None], -1)  # s_j . I_i s_m
    mass = jnp.sum(above[:, :, None] * above[:, None, :] * sis, axis=0)
    mass = mass + jnp.diag(sys.dof.armature)
    return tuple(tuple(row) for row in mass), tuple(bias)


# Up to this many dofs a step is unrolled over scalars (a few elementwise loops, as fast as
# the closed forms of `analytic`); beyond, XLA's fuser recomputes the unrolled shared terms in
# every consumer (a 4-dof tree's gradient rollout took minutes to compile), so larger trees
# run on [bodies, ...] arrays, summed along the static ancestor matrix.
_UNROLL_MAX_DOFS = 3


def _dynamics(sys, q, qd):
    """Mass matrix M (armature included) and the bias forces, as nested tuples of scalars."""
    if q.shape[0] <= _UNROLL_MAX_DOFS:
        return _unrolled_dynamics(sys, list(q), list(qd))
    return _stacked_dynamics(sys, q, qd)


def _cholesky(a):
    """Lower factor of a small SPD matrix, unrolled (no LAPACK call per batch element)."""
    n = len(a)
    low = [[0.0] * n for _ in range(n)]
    for j in range(n):
        low[j][j] = jnp.sqrt(_sub(a[j][j], _sum(_mul(low[j][k], low[j][k]) for k in range(j))))
        for i in range(j + 1, n):
            rest = _sum(_mul(low[i][k], low[j][k]) for k in range(j))
            low[i][j] = _sub(a[i][j], rest) / low[j][j]
    return low


def _forward(low, b):
    """y with L y = b (zeros of b that lead stay exact zeros)."""
    y = []
    for i, bi in enumerate(b):
        rest = _sub(bi, _sum(_mul(low[i][k], y[k]) for k in range(i)))
        y.append(0.0 if _is(rest, 0.0) else rest / low[i][i])
    return y


def _solve(low, b):
    """x with (L L^T) x = b, L from `_cholesky`."""
    y, x = _forward(low, b), [0.0] * len(b)
    for i in reversed(range(len(b))):
        x[i] = _sub(y[i], _sum(_mul(low[k][i], x[k]) for k in range(i + 1, len(b)))) / low[i][i]
    return x


def _limit_force(sys, q, qd, force, mass, h):
    """MuJoCo's soft joint-limit forces given the smooth forces and the mass matrix.

    The forces lam >= 0 of the active limits minimise 0.5 lam (A + R) lam - lam b, with A the
    limits' block of M^-1 (signed by each limit's side), R the regulariser and b the reference
    acceleration less the unconstrained one: MuJoCo's constraint problem, which its solver
    solves exactly. One limited dof: the clipped closed form. Several: a primal-dual active-set
    method, as many passes as limited dofs plus one (each an unrolled solve). None when the
    model has no limited joint."""
    terms = limit_terms(sys, q, qd, h)
    if terms is None:
        return None
    dofs, active, side, aref, reg = terms
    n, k = q.shape[0], dofs.size
    low = _cholesky(mass)
    free = _solve(low, force)
    b = aref - side * jnp.stack([free[d] for d in dofs])
    # A = E^T M^-1 E = (L^-1 E)^T (L^-1 E), E the limited dofs' columns of the identity
    halves = [_forward(low, [float(i == d) for i in range(n)]) for d in dofs]
    a = jnp.stack([jnp.stack([_dot(x, y) for y in halves]) for x in halves])
    a = a * side[:, None] * side[None, :] + jnp.diag(reg)
    if k == 1:
        lam = jnp.maximum(0.0, b / a[0, 0])
    else:
        chosen, eye = active, jnp.eye(k)
        for _ in range(k + 1):
            mask = chosen.astype(b.dtype)
            system = a * mask[:, None] * mask[None, :] + eye * (1 - mask)
            lam = jnp.stack(_solve(_cholesky(system), list(b * mask)))
            slack = jnp.sum(a * lam[None, :], axis=1) - b  # >= 0 where a limit is left out
            chosen = active & (lam * jnp.diagonal(a) - slack > 0)
        lam = jnp.maximum(lam, 0.0)
    return put(jnp.where(active, side * lam, 0.0), dofs, n)


def step(sys, state: State, act: jax.Array, *args, **kwargs) -> State:
    """One MuJoCo-style Euler step of `sys.opt.timestep` under actuator inputs `act`.

    Rematerialised: reverse mode recomputes the step from its inputs instead of storing its
    hundreds of scalar intermediates for every step of a rollout, which compiles several
    times faster and runs the backward pass faster too (bench/engine.py)."""
    del args, kwargs
    return jax.checkpoint(lambda s, a: _euler_step(sys, s, a))(state, act)


def _euler_step(sys, state: State, act: jax.Array) -> State:
    h = sys.opt.timestep
    q, qd = state.q, state.qd
    n = q.shape[0]
    mass, bias = _dynamics(sys, q, qd)
    damping, stiffness = _values(sys.dof.damping), _values(sys.dof.stiffness)
    tau = actuator.to_tau(sys, act, q, qd)
    force = [
        _sub(_sub(_sub(tau[i], bias[i]), _mul(damping[i], qd[i])), _mul(stiffness[i], q[i]))
        for i in range(n)
    ]
    limit = _limit_force(sys, q, qd, force, mass, h)
    if limit is not None:
        force = [_add(f, limit[i]) for i, f in enumerate(force)]
    step_h = _values(h)
    damped = [
        [_add(m, _mul(step_h, damping[i])) if i == j else m for j, m in enumerate(row)]
        for i, row in enumerate(mass)
    ]
    qdd = jnp.stack(_solve(_cholesky(damped), force))
    qd = qd + h * qdd
    return State(q=q + h * qd, qd=qd, qdd=qdd)
