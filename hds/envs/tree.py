"""A physics backend for any kinematic tree of hinge and slide joints, without contacts.

It has the functional interface of brax's pipelines (`init`, `step`, a `State` with `q` and
`qd`), like `hds.envs.analytic`, whose closed forms it generalises: `make_simulator(...,
backend="tree")`. The tree's structure (parents, joint types) is static, so a step unrolls
over the bodies at trace time into a few hundred scalar and 3x3/6x6 operations.

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

import jax
import jax.numpy as jnp
import numpy as np
from brax import actuator

from hds.envs.analytic import (
    State,
    check_options,
    init,
    limit_terms,
    put,
    quat_matrix,
    system_geometry,
    take,
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


def _constants(sys) -> dict:
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


def _cross_motion(v, m):
    """Spatial motion cross products v x m, row by row; [n, 6] (angular, linear at the origin)."""
    w, u = v[:, :3], v[:, 3:]
    return jnp.concatenate(
        [jnp.cross(w, m[:, :3]), jnp.cross(w, m[:, 3:]) + jnp.cross(u, m[:, :3])], axis=1
    )


def _cross_force(v, f):
    """Spatial force cross products v x* f, row by row."""
    w, u = v[:, :3], v[:, 3:]
    return jnp.concatenate(
        [jnp.cross(w, f[:, :3]) + jnp.cross(u, f[:, 3:]), jnp.cross(w, f[:, 3:])], axis=1
    )


def _kinematics(sys, g, q):
    """World frames of the bodies at q, body by body down the tree: rotations [n, 3, 3],
    centres of mass [n, 3] and joint motion subspaces [n, 6] about the world origin."""
    rots, origins, coms, subspaces = [], [], [], []
    for i, parent in enumerate(sys.link_parents):
        if parent < 0:
            frame, origin = jnp.asarray(g["rot"][i]), jnp.asarray(g["pos"][i])
        else:
            frame = rots[parent] @ g["rot"][i]
            origin = origins[parent] + rots[parent] @ g["pos"][i]
        axis = frame @ g["axis"][i]
        if g["hinge"][i]:  # rotate about the anchor, which stays put
            anchor = origin + frame @ g["jpos"][i]
            turn = jnp.sin(q[i]) * g["k"][i] + (1 - jnp.cos(q[i])) * g["k2"][i]
            frame = frame + frame @ turn
            origin = anchor - frame @ g["jpos"][i]
            subspaces.append(jnp.concatenate([axis, jnp.cross(anchor, axis)]))
        else:
            origin = origin + axis * q[i]
            subspaces.append(jnp.concatenate([jnp.zeros(3), axis]))
        rots.append(frame)
        origins.append(origin)
        coms.append(origin + frame @ g["ipos"][i])
    return jnp.stack(rots), jnp.stack(coms), jnp.stack(subspaces)


def _spatial_inertias(sys, g, rots, coms):
    """[n, 6, 6] inertias about the world origin, in world axes."""
    mass = sys.link.inertia.mass
    principal = rots @ g["irot"]
    inertia = principal @ sys.link.inertia.i @ jnp.swapaxes(principal, 1, 2)
    c = _skew(coms)
    m = mass[:, None, None]
    top = jnp.concatenate([inertia + m * jnp.swapaxes(c, 1, 2) @ c, m * c], axis=2)
    bottom = jnp.concatenate([m * jnp.swapaxes(c, 1, 2), m * jnp.eye(3)], axis=2)
    return jnp.concatenate([top, bottom], axis=1)


def _dynamics(sys, q, qd):
    """Mass matrix M (armature included) and the bias forces (Coriolis, centrifugal, gravity).

    Vectorised over the bodies with the static ancestor matrix: velocities and velocity-product
    accelerations sum down the tree, forces sum up it (recursive Newton-Euler with qdd = 0 and
    gravity as an upward acceleration of the world); M[j, k] = sum over bodies i below both
    j and k of s_j . I_i s_k (composite rigid bodies)."""
    g = _constants(sys)
    above = g["above"]
    rots, coms, s = _kinematics(sys, g, q)
    inertia = _spatial_inertias(sys, g, rots, coms)
    joint = s * qd[:, None]
    vel = above @ joint
    base = jnp.concatenate([jnp.zeros(3), -jnp.asarray(g["gravity"], q.dtype)])
    acc = base + above @ _cross_motion(vel, joint)
    momentum = jnp.einsum("ikl,il->ik", inertia, vel)
    force = jnp.einsum("ikl,il->ik", inertia, acc) + _cross_force(vel, momentum)
    bias = jnp.sum(s * (above.T @ force), axis=1)
    sis = jnp.einsum("jk,ikl,ml->ijm", s, inertia, s)  # s_j . I_i s_m
    mass = jnp.einsum("ij,im,ijm->jm", above, above, sis)
    return mass + jnp.diag(sys.dof.armature), bias


def _cholesky(a):
    """Lower factor of a small SPD matrix, unrolled (no LAPACK call per batch element)."""
    n = a.shape[0]
    low = [[None] * n for _ in range(n)]
    for j in range(n):
        d = a[j, j] - sum(low[j][k] ** 2 for k in range(j))
        low[j][j] = jnp.sqrt(d)
        for i in range(j + 1, n):
            low[i][j] = (a[i, j] - sum(low[i][k] * low[j][k] for k in range(j))) / low[j][j]
    return low


def _solve(low, b):
    """Solve (L L^T) x = b with the factor of `_cholesky`; entries of b may be Python zeros,
    which the unrolled substitution skips."""
    n = len(low)
    y = []
    for i in range(n):
        rest = sum(low[i][k] * y[k] for k in range(i) if y[k] is not None)
        y.append(
            None
            if (b[i] is None and isinstance(rest, int))
            else ((0 if b[i] is None else b[i]) - rest) / low[i][i]
        )
    x = [None] * n
    for i in reversed(range(n)):
        rest = sum(low[k][i] * x[k] for k in range(i + 1, n))
        x[i] = ((0 if y[i] is None else y[i]) - rest) / low[i][i]
    return jnp.stack(x)


def _limit_force(sys, q, qd, force, low, h):
    """MuJoCo's soft joint-limit forces given the smooth forces and M's factor.

    The forces lam >= 0 of the active limits minimise 0.5 lam (A + R) lam - lam b, with A the
    limits' block of M^-1 (signed by each limit's side), R the regulariser and b the reference
    acceleration less the unconstrained one: MuJoCo's constraint problem, which its solver
    solves exactly. One limited dof: the clipped closed form. Several: a primal-dual active-set
    method, as many passes as limited dofs plus one (each an unrolled solve)."""
    terms = limit_terms(sys, q, qd, h)
    if terms is None:
        return jnp.zeros_like(q)
    dofs, active, side, aref, reg = terms
    n, k = q.shape[0], dofs.size
    b = aref - side * take(_solve(low, list(force)), dofs)
    columns = [_solve(low, [1.0 if i == d else None for i in range(n)]) for d in dofs]
    a = jnp.stack([take(c, dofs) for c in columns]) * side[:, None] * side[None, :]
    a = a + jnp.diag(reg)
    if k == 1:
        lam = jnp.maximum(0.0, b / a[0, 0])
    else:
        chosen, eye = active, jnp.eye(k)
        for _ in range(k + 1):
            mask = chosen.astype(b.dtype)
            system = a * mask[:, None] * mask[None, :] + eye * (1 - mask)
            lam = _solve(_cholesky(system), list(b * mask))
            slack = a @ lam - b  # >= 0 where a limit is left out
            chosen = active & (lam * jnp.diagonal(a) - slack > 0)
        lam = jnp.maximum(lam, 0.0)
    return put(jnp.where(active, side * lam, 0.0), dofs, n)


def step(sys, state: State, act: jax.Array, *args, **kwargs) -> State:
    """One MuJoCo-style Euler step of `sys.opt.timestep` under actuator inputs `act`."""
    del args, kwargs
    h = sys.opt.timestep
    q, qd = state.q, state.qd
    mass, bias = _dynamics(sys, q, qd)
    damping = sys.dof.damping
    force = actuator.to_tau(sys, act, q, qd) - bias - damping * qd - sys.dof.stiffness * q
    force = force + _limit_force(sys, q, qd, force, _cholesky(mass), h)
    qdd = _solve(_cholesky(mass + jnp.diag(h * damping)), list(force))
    qd = qd + h * qdd
    return State(q=q + h * qd, qd=qd, qdd=qdd)
