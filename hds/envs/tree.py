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

What it models, read from the System (brax's fields, hds.envs.mjsystem) on every step (so
effects that edit the System, mass_scale on `link.inertia` and actuator_gain on
`actuator.gear`, act on it):
  - rigid-body dynamics in world coordinates (spatial vectors about the world origin): the
    composite-rigid-body mass matrix and recursive Newton-Euler bias forces (Coriolis,
    centrifugal, gravity), from masses, COM offsets, inertia tensors and their principal
    frames, body frames, joint anchors and axes of any direction, gravity of any direction;
  - joint armature, damping (implicit, as MuJoCo's Euler), stiffness with spring reference 0;
  - actuators as `brax.actuator.to_tau` (hds.envs.mjsystem.to_tau: gear, gain, bias, ctrl and
    force clipping; the unlimited motors through which effect forces enter);
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

from hds.envs.analytic import (
    State,
    check_options,
    concrete,
    init,
    limit_terms,
    quat_matrix,
    system_geometry,
)
from hds.envs.mjsystem import to_tau

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
    """Per body, its frame and joint relative to its parent. Only the centres of mass are
    edited by effects (com_scale): when they alone are traced, everything else stays folded
    (a traced frame multiplies a step's operations, and its compile time, several times)."""
    parts, xp = system_geometry(sys)
    if xp is not np:
        rest = [k for k in parts if k != "ipos"]
        known = concrete([parts[k] for k in rest])
        if known is not None:
            parts, xp = dict(zip(rest, known)) | {"ipos": parts["ipos"]}, np
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
# What a gradient rollout's compile time follows is the count of XLA's fused kernels: each
# reduction ends one, and so does the gradient of each slice (a padded copy). So a step is
# arranged around few of both: the joints enter every body's placement elementwise, for all
# bodies at once, and one product per body places it in the world; sums along the tree
# (velocities down it, forces up it) and the composite inertias are sums over the static
# ancestor matrix; cross products are sums over a constant basis, not components sliced out.


def _stacked_constants(sys) -> dict:
    """Per body, its placement in its parent's frame as constant columns (numpy when known at
    trace time, else traced), so that the joint enters through elementwise products only.

    A body's placement is the [4, 10] matrix `C0 + x1 C1 + x2 C2` with (x1, x2) = (sin q,
    1 - cos q) for a hinge (rotation I + sin K + (1 - cos) K^2 about its axis, K = [axis]x)
    and (q, 0) for a slide. Its columns, in the parent's frame: the body's rotation (3) and
    origin, its inertia's principal axes (3), the joint axis, the anchor and the centre of
    mass; the last row is homogeneous (1 under the three points), so that one product with
    the parent's [3, 4] world placement [rotation | origin] gives all of them in the world.
    Stacked over the bodies: C0, C1, C2 [n, 4, 10]."""
    parts, xp = system_geometry(sys)
    hinges = [bool(np.any(np.asarray(a) != 0)) for a in np.asarray(sys.dof.motion.ang)]
    places = []
    for i, hinge in enumerate(hinges):
        axis = parts["ang"][i] if hinge else parts["vel"][i]
        axis = axis / xp.linalg.norm(axis)
        rot, pos = quat_matrix(parts["rot"][i], xp), parts["pos"][i]
        irot, ipos, jpos = quat_matrix(parts["irot"][i], xp), parts["ipos"][i], parts["jpos"][i]
        zero3, zero = xp.zeros((3, 3)), xp.zeros(3)
        if hinge:
            turn = xp.cross(xp.eye(3), axis)  # K
            terms = [rot @ turn, rot @ turn @ turn]  # the columns times sin and 1 - cos
            arm = ipos - jpos
            c1, c2 = (
                xp.concatenate(
                    [t, -(t @ jpos)[:, None], t @ irot, xp.stack([zero, zero, t @ arm], 1)], 1
                )
                for t in terms
            )
        else:
            moved = rot @ axis
            c1 = xp.concatenate([zero3, moved[:, None], zero3, xp.stack([zero, zero, moved], 1)], 1)
            c2 = xp.zeros_like(c1)
        points = [rot @ axis, pos + rot @ jpos, pos + rot @ ipos]
        c0 = xp.concatenate([rot, pos[:, None], rot @ irot, xp.stack(points, axis=1)], axis=1)
        homogeneous = xp.asarray([0.0] * 3 + [1.0] + [0.0] * 4 + [1.0] * 2)[None]
        places.append(
            (
                xp.concatenate([c0, homogeneous]),
                xp.concatenate([c1, 0 * homogeneous]),
                xp.concatenate([c2, 0 * homogeneous]),
            )
        )
    c0, c1, c2 = (xp.stack(c) for c in zip(*places, strict=True))
    return {"hinge": np.asarray(hinges), "places": (c0, c1, c2), "gravity": parts["gravity"]}


def _mm(a, b):
    """a @ b over the last two axes, as a broadcast product and one sum: under vmap a matmul
    becomes a batched dot, a kernel of its own per product, which costs more than its sum."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


_CROSS_BASIS = np.cross(np.eye(3)[:, None], np.eye(3)[None]).transpose(0, 2, 1)  # [e_k]x, by k


def _cross_last(u, v):
    """Cross products along the last axis (3) of broadcastable arrays, as one sum over the
    constant basis [e_k]x: jnp.cross slices out every component, and the gradient of each
    slice is a padded copy, a kernel of its own."""
    return jnp.sum(u[..., :, None, None] * _CROSS_BASIS * v[..., None, None, :], axis=(-3, -1))


def _blocks(x):
    """[..., 6] -> [..., 2, 3]: a spatial vector's angular and linear halves."""
    return x.reshape(x.shape[:-1] + (2, 3))


def _cross_motion6(v, m):
    """Spatial motion cross product v x m of [..., 6] (angular, linear at the origin):
    (w x m_ang, w x m_lin + u x m_ang) for v = (w, u)."""
    both = _cross_last(v[..., None, :3], _blocks(m)).reshape(m.shape)
    extra = _cross_last(v[..., 3:], m[..., :3])
    return both + jnp.concatenate([jnp.zeros_like(extra), extra], axis=-1)


def _cross_force6(v, f):
    """Spatial force cross product v x* f: (w x f_ang + u x f_lin, w x f_lin)."""
    both = _cross_last(v[..., None, :3], _blocks(f)).reshape(f.shape)
    extra = _cross_last(v[..., 3:], f[..., 3:])
    return both + jnp.concatenate([extra, jnp.zeros_like(extra)], axis=-1)


def _stacked_kinematics(sys, g, q):
    """World placement of the bodies at q, down the tree (one product per body with a
    parent): principal inertia axes [n, 3, 3], centres of mass [n, 3] and joint motion
    subspaces [n, 6] (angular, linear about the world origin)."""
    c0, c1, c2 = g["places"]
    hinge = g["hinge"].astype(np.float32)
    x1 = jnp.where(g["hinge"], jnp.sin(q), q)
    x2 = hinge * (1 - jnp.cos(q))
    local = c0 + x1[:, None, None] * c1 + x2[:, None, None] * c2
    worlds = []
    for i, parent in enumerate(int(p) for p in sys.link_parents):
        worlds.append(local[i, :3] if parent < 0 else _mm(worlds[parent][:, :4], local[i]))
    world = jnp.stack(worlds)
    axis, anchor = world[:, :, 7], world[:, :, 8]
    hinge = hinge[:, None]
    s = jnp.concatenate([hinge * axis, hinge * _cross_last(anchor, axis) + (1 - hinge) * axis], 1)
    return world[:, :, 4:7], world[:, :, 9], s


def _spatial_inertias(sys, principal, coms):
    """[n, 6, 6] inertias about the world origin, in world axes: [[J, [h]x], [-[h]x, m]] with
    h = m c and J = I_c + m (|c|^2 - c c^T)."""
    mass = sys.link.inertia.mass[:, None, None]
    rotated = _mm(_mm(principal, sys.link.inertia.i), jnp.swapaxes(principal, 1, 2))
    square = coms[:, 0] ** 2 + coms[:, 1] ** 2 + coms[:, 2] ** 2
    eye = jnp.eye(3)
    shifted = rotated + mass * (square[:, None, None] * eye - coms[:, :, None] * coms[:, None, :])
    skew = jnp.sum((mass * coms[:, :, None])[..., None] * _CROSS_BASIS, axis=1)  # [m c]x
    top = jnp.concatenate([shifted, skew], axis=2)
    bottom = jnp.concatenate([-skew, mass * eye], axis=2)
    return jnp.concatenate([top, bottom], axis=1)


def _stacked_dynamics(sys, q, qd):
    """Mass matrix M (armature included) and the bias forces (Coriolis, centrifugal, gravity),
    as nested tuples of scalars.

    Vectorised over the bodies with the static ancestor matrix: velocities and velocity-product
    accelerations sum down the tree, forces sum up it (recursive Newton-Euler with qdd = 0 and
    gravity as an upward acceleration of the world); M[j, k] = sum over bodies i below both
    j and k of s_j . I_i s_k (composite rigid bodies)."""
    g = _stacked_constants(sys)
    above = _tree_matrix(sys.link_parents)
    principal, coms, s = _stacked_kinematics(sys, g, q)
    inertia = _spatial_inertias(sys, principal, coms)
    joint = s * qd[:, None]
    vel = _down(above, joint)
    base = jnp.concatenate([jnp.zeros(3), -jnp.asarray(g["gravity"], q.dtype)])
    acc = base + _down(above, _cross_motion6(vel, joint))
    products = _mm(inertia, jnp.stack([vel, acc], axis=2))  # [n, 6, 2]
    force = products[:, :, 1] + _cross_force6(vel, products[:, :, 0])
    bias = jnp.sum(s * _down(above.T, force), axis=1)
    inertia_s = _mm(inertia, s.T)  # [i, 6, m]: I_i s_m
    mass = jnp.einsum("ij,im,jr,irm->jm", above, above, s, inertia_s)
    mass = mass + jnp.diag(sys.dof.armature)
    return tuple(tuple(row) for row in mass), tuple(bias)


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


def _down(above, x):
    """above @ x for the static [n, n] ancestor matrix and x [n, 6]."""
    return jnp.sum(above[:, :, None] * x[None], axis=1)


# Up to this many dofs a step is unrolled over scalars (a few elementwise loops, as fast as
# the closed forms of `analytic`); beyond, XLA's fuser recomputes the unrolled shared terms in
# every consumer (the skewed 4-dof tree's gradient rollout unrolled: 37 s to compile and 5 s
# a call, against 7 s and 0.05 s stacked; no better with optimization barriers between the
# stages), so larger trees run on [bodies, ...] arrays.
_UNROLL_MAX_DOFS = 3


def _dynamics(sys, q, qd):
    """Mass matrix M (armature included) and the bias forces, as nested tuples of scalars."""
    if q.shape[0] <= _UNROLL_MAX_DOFS:
        return _unrolled_dynamics(sys, list(q), list(qd))
    return _stacked_dynamics(sys, q, qd)


def _cholesky(a):
    """Lower factor of a small SPD matrix, unrolled (no LAPACK call per batch element), with
    the reciprocals of its diagonal in place of the diagonal: one rsqrt per column, and every
    division of the solves a multiplication (each division is a fused kernel of its own)."""
    n = len(a)
    low = [[0.0] * n for _ in range(n)]
    for j in range(n):
        low[j][j] = _rsqrt(_sub(a[j][j], _sum(_mul(low[j][k], low[j][k]) for k in range(j))))
        for i in range(j + 1, n):
            rest = _sum(_mul(low[i][k], low[j][k]) for k in range(j))
            low[i][j] = _mul(_sub(a[i][j], rest), low[j][j])
    return low


def _rsqrt(x):
    return x**-0.5 if isinstance(x, float) else jax.lax.rsqrt(x)


def _forward(low, b):
    """y with L y = b (zeros of b that lead stay exact zeros)."""
    y = []
    for i, bi in enumerate(b):
        y.append(_mul(_sub(bi, _sum(_mul(low[i][k], y[k]) for k in range(i))), low[i][i]))
    return y


def _solve(low, b):
    """x with (L L^T) x = b, L from `_cholesky`."""
    y, x = _forward(low, b), [0.0] * len(b)
    for i in reversed(range(len(b))):
        rest = _sum(_mul(low[k][i], x[k]) for k in range(i + 1, len(b)))
        x[i] = _mul(_sub(y[i], rest), low[i][i])
    return x


def _limit_force(sys, q, qd, force, mass, h):
    """MuJoCo's soft joint-limit forces given the smooth forces and the mass matrix.

    The forces lam >= 0 of the active limits minimise 0.5 lam (A + R) lam - lam b, with A the
    limits' block of M^-1 (signed by each limit's side), R the regulariser and b the reference
    acceleration less the unconstrained one: MuJoCo's constraint problem, which its solver
    solves exactly. One limited dof: the clipped closed form. Several: a primal-dual active-set
    method, as many passes as limited dofs plus one (each an unrolled solve). Per limited dof
    its force ({dof: force}); None when the model has no limited joint."""
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
    forces = jnp.where(active, side * lam, 0.0)
    return {int(d): forces[i] for i, d in enumerate(dofs)}


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
    tau = to_tau(sys, act, q, qd)
    force = [
        _sub(_sub(_sub(tau[i], bias[i]), _mul(damping[i], qd[i])), _mul(stiffness[i], q[i]))
        for i in range(n)
    ]
    limit = _limit_force(sys, q, qd, force, mass, h)
    if limit is not None:
        force = [_add(f, limit.get(i, 0.0)) for i, f in enumerate(force)]
    step_h = _values(h)
    damped = [
        [_add(m, _mul(step_h, damping[i])) if i == j else m for j, m in enumerate(row)]
        for i, row in enumerate(mass)
    ]
    qdd = jnp.stack(_solve(_cholesky(damped), force))
    qd = qd + h * qdd
    return State(q=q + h * qd, qd=qd, qdd=qdd)
