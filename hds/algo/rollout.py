"""Rollouts on an engine: anything with pure reset(key), step(state, u, params),
observe(state, params) and qqd(state) (the simulator, or a learned dynamics model)."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def policy_rollout(engine, params, task, act, state, key, noise_std, horizon, low, high):
    """Closed loop: u_t = clip(act(o_t) + noise). Returns (obs [T, n_obs], u [T, n_act], r [T])."""
    n_act = low.shape[0]
    noise = jax.vmap(lambda k: jax.random.normal(k, (n_act,)))(jax.random.split(key, horizon))
    return perturbed_rollout(engine, params, task, act, state, noise_std * noise, low, high)


def perturbed_rollout(engine, params, task, act, state, deltas, low, high, window=0):
    """Closed loop with a perturbation per step: u_t = clip(act(o_t) + deltas_t).
    Returns (obs [T, n_obs], u [T, n_act], r [T]).

    `window` > 0 truncates gradients as SHAC does: the state is cut from the gradient every
    `window` steps, so a perturbation's gradient sums only the rewards up to the end of its
    window (values are unchanged). Through many steps of a chaotic system (a pole swinging over
    the top) the full gradient explodes and points nowhere useful."""

    def step(state, xs):
        t, delta = xs
        if window:
            cut = t % window == 0
            state = jax.tree.map(lambda s: jnp.where(cut, jax.lax.stop_gradient(s), s), state)
        obs = engine.observe(state, params)
        u = jnp.clip(act(obs) + delta, low, high)
        state = engine.step(state, u, params)
        return state, (obs, u, task.reward(*engine.qqd(state), u))

    _, (obs, u, r) = jax.lax.scan(step, state, (jnp.arange(deltas.shape[0]), deltas))
    return obs, u, r


def trajectory(engine, params, task, state, actions):
    """Open loop: the true states reached [T, nq + nv] and the rewards [T]."""

    def step(state, u):
        state = engine.step(state, u, params)
        q, qd = engine.qqd(state)
        return state, (jnp.concatenate([q, qd]), task.reward(q, qd, u))

    return jax.lax.scan(step, state, actions)[1]


def open_loop_return(engine, params, task, state, actions):
    """The return of an action sequence: the reward of every state reached, the last included."""
    return trajectory(engine, params, task, state, actions)[1].sum()
