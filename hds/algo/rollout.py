"""Rollouts on an engine: anything with pure reset(key), step(state, u, params),
observe(state, params) and qqd(state) (the simulator, or a learned dynamics model).

A policy that sees its last command (`last_command`, hds.networks.Policy) gets the input
[o_t, u_{t-1}] (zeros at a rollout's start): the controller remembers what it sent, as a real
one does, which a delay in the actuator otherwise hides from it. The rollouts return the
observations alone; `policy_inputs` rebuilds what the policy saw from them and the controls.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def policy_inputs(obs, controls, last_command: bool):
    """What a policy saw along a rollout: obs [..., T, n_obs], or, where it sees its last
    command, [obs_t, u_{t-1}] [..., T, n_obs + n_act] with zeros before the first control."""
    if not last_command:
        return obs
    before = jnp.zeros_like(controls[..., :1, :])
    return jnp.concatenate([obs, jnp.concatenate([before, controls[..., :-1, :]], -2)], -1)


def policy_rollout(
    engine, params, task, act, state, key, noise_std, horizon, low, high, last_command=False
):
    """Closed loop: u_t = clip(act(o_t) + noise). Returns (obs [T, n_obs], u [T, n_act], r [T])."""
    n_act = low.shape[0]
    noise = jax.vmap(lambda k: jax.random.normal(k, (n_act,)))(jax.random.split(key, horizon))
    return perturbed_rollout(
        engine, params, task, act, state, noise_std * noise, low, high, last_command=last_command
    )


def perturbed_rollout(
    engine, params, task, act, state, deltas, low, high, window=0, last_command=False
):
    """Closed loop with a perturbation per step: u_t = clip(act(o_t) + deltas_t) (with
    `last_command`: act([o_t, u_{t-1}])). Returns (obs [T, n_obs], u [T, n_act], r [T]).

    `window` > 0 truncates gradients as SHAC does: the state is cut from the gradient every
    `window` steps, so a perturbation's gradient sums only the rewards up to the end of its
    window (values are unchanged). Through many steps of a chaotic system (a pole swinging over
    the top) the full gradient explodes and points nowhere useful."""

    def cut(t, tree):
        if not window:
            return tree
        at = t % window == 0
        return jax.tree.map(lambda s: jnp.where(at, jax.lax.stop_gradient(s), s), tree)

    def step_with(feedback):
        def step(state, xs):
            t, delta = xs
            state = cut(t, state)
            obs = engine.observe(state, params)
            u = jnp.clip(feedback(obs) + delta, low, high)
            state = engine.step(state, u, params)
            return state, (obs, u, task.reward(*engine.qqd(state), u))

        return step

    xs = (jnp.arange(deltas.shape[0]), deltas)
    if not last_command:
        _, (obs, u, r) = jax.lax.scan(step_with(act), state, xs)
        return obs, u, r

    def remembering(carry, xs):  # the last command is cut from the gradient with the state
        state, last = cut(xs[0], carry)
        state, out = step_with(lambda obs: act(jnp.concatenate([obs, last])))(state, xs)
        return (state, out[1]), out

    _, (obs, u, r) = jax.lax.scan(remembering, (state, jnp.zeros_like(deltas[0])), xs)
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
