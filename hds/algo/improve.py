"""Improve one action sequence with the analytic gradient of its return (PODS, step 2).

  first order   a' = a + alpha g                        g = dV/da, clipped by global norm
  second order  a' = a + alpha (H + lambda I)^-1 g      H: Gauss-Newton curvature of the cost

The candidate step sizes alpha / 2^k are evaluated together, as one batched rollout, and then
accepted by the step-size rule of `anneal` (hds/anneal.py). A sequence whose return or gradient
is not finite is left as it was and reported as skipped; candidates are clipped to the
actuator's range. With `counted` steps (anneal.horizon_start, a curriculum), only their
rewards count.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from hds.algo.rollout import perturbed_rollout, trajectory
from hds.anneal import accept


class ImproveSettings(NamedTuple):
    order: str  # first | second
    grad_clip: float
    gn_damping: float
    candidates: int  # step sizes alpha / 2^k tried together
    anneal: str  # the acceptance rule: line_search | simulated | fixed
    grad_window: int = 0  # closed loop: truncate gradients to windows of this many steps


class Improved(NamedTuple):
    actions: jax.Array  # [T, n_act]
    value: jax.Array  # return before
    new_value: jax.Array  # return after (equal to value when nothing was accepted)
    accepted: jax.Array  # bool
    skipped: jax.Array  # bool: non-finite return or gradient


def psd(matrix: jax.Array) -> jax.Array:
    """Project a symmetric matrix onto the positive semi-definite cone."""
    w, v = jnp.linalg.eigh(0.5 * (matrix + matrix.T))
    return (v * jnp.maximum(w, 0.0)) @ v.T


def gauss_newton_matrix(engine, params, task, state, actions, counted=None) -> jax.Array:
    """H = J^T Hs J + Ha for the cost C = -V, with J = d(states)/d(actions) and Hs, Ha the
    per-step cost Hessians (projected to PSD) of the `counted` steps ([T] weights; default all);
    second-order terms of the dynamics are dropped."""
    T, n_act = actions.shape
    states = lambda a: trajectory(engine, params, task, state, a)[0]  # noqa: E731
    s = states(actions)
    J = jax.jacfwd(states)(actions).reshape(*s.shape, T * n_act)  # [T, n_state, T * n_act]
    nq = len(task.q_mean)

    def step_cost(s_t, u_t):
        return -task.reward(s_t[:nq], s_t[nq:], u_t)

    Hs = jax.vmap(lambda s_t, u_t: psd(jax.hessian(step_cost, 0)(s_t, u_t)))(s, actions)
    Ha = jax.vmap(lambda s_t, u_t: psd(jax.hessian(step_cost, 1)(s_t, u_t)))(s, actions)
    if counted is not None:
        Hs, Ha = Hs * counted[:, None, None], Ha * counted[:, None, None]
    H = jnp.einsum("tia,tij,tjb->ab", J, Hs, J)
    return H + jax.scipy.linalg.block_diag(*Ha)


def gauss_newton_step(H: jax.Array, g: jax.Array, damping: float) -> jax.Array:
    """Solve (H + lambda I) d = g with lambda relative to H's scale (Cholesky, no inverse)."""
    lam = damping * jnp.mean(jnp.diag(H)) + 1e-6
    factor = jax.scipy.linalg.cho_factor(H + lam * jnp.eye(H.shape[0]))
    return jax.scipy.linalg.cho_solve(factor, g)


def improve(
    engine,
    params,
    task,
    state,
    actions,
    key,
    *,
    alpha,
    temperature,
    cfg,
    low,
    high,
    act=None,
    counted=None,
):
    """One action-improvement step for one sequence; `cfg` holds algo and anneal settings.

    With `act` (the policy, o -> u), `actions` are perturbations of the closed loop,
    u_t = clip(act(o_t) + actions_t), and the return is differentiated through the policy's
    feedback (first order only); otherwise they are the open-loop controls (PODS). `counted`
    ([T] weights, may be traced; hds.algo.continuation.counted_steps): weigh each step's
    reward; None: all."""
    if act is None:
        rewards = lambda a: trajectory(engine, params, task, state, a)[1]  # noqa: E731
    else:
        rewards = lambda d: perturbed_rollout(  # noqa: E731  (a window leaves values as they are)
            engine, params, task, act, state, d, low, high, cfg.grad_window
        )[2]
        low, high = low - high, high - low  # a perturbation may span the whole range
    if counted is None:
        ret = lambda a: rewards(a).sum()  # noqa: E731
    else:
        ret = lambda a: jnp.dot(rewards(a), counted)  # noqa: E731
    value, grad = jax.value_and_grad(ret)(actions)
    grad, _ = optax.clip_by_global_norm(cfg.grad_clip).update(grad, None)
    finite = jnp.isfinite(value) & jnp.all(jnp.isfinite(grad))
    grad = jnp.where(finite, grad, 0.0)

    if cfg.order == "second":
        H = gauss_newton_matrix(engine, params, task, state, actions, counted)
        step = gauss_newton_step(H, grad.reshape(-1), cfg.gn_damping).reshape(actions.shape)
        finite &= jnp.all(jnp.isfinite(step))
        direction = jnp.where(finite, step, 0.0)
    else:
        direction = grad

    scales = alpha * 0.5 ** jnp.arange(cfg.candidates)
    candidates = jnp.clip(actions + scales[:, None, None] * direction, low, high)
    values = jax.vmap(ret)(candidates)
    values = jnp.where(jnp.isfinite(values), values, -jnp.inf)
    best = jnp.argmax(values)
    ok = finite & accept(cfg.anneal, values[best], value, temperature, key)
    return Improved(
        actions=jnp.where(ok, candidates[best], actions),
        value=value,
        new_value=jnp.where(ok, values[best], value),
        accepted=ok,
        skipped=~finite,
    )
