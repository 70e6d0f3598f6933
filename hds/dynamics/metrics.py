"""Open-loop k-step prediction error on held-out episodes, for a model and for a baseline.

From every observation obs[e, t] of an episode (t <= T - k) the step function is iterated k
times with the recorded actions actions[e, t .. t+k-1], and its prediction compared with
obs[e, t+k]. Hinge-angle errors are wrapped to [-pi, pi). Per variable the error is a root mean
square over all windows; the score `nrmse` divides each by the spread (std) of that variable
in the held-out data and averages over variables (1 means as far off as the data's spread).

`closed_loop_returns`: a policy's return run through a model, the loop HDS's rollouts close.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from hds.dynamics.model import wrap_angles


def open_loop_predictions(step: Callable, obs, actions, kmax: int) -> np.ndarray:
    """[E, T, kmax, n_obs]: from each obs[e, t], the state after 1..kmax steps of `step(obs, u)`
    (windows running past the episode's end repeat its last action; they are never scored).
    `step` is a static argument of one jitted function: the same step function on the same
    shapes compiles once (keep it the same object, e.g. a model's bound `predict`)."""
    obs, actions = jnp.asarray(obs, jnp.float32), jnp.asarray(actions, jnp.float32)
    E, T, _ = actions.shape
    index = np.minimum(np.arange(T)[:, None] + np.arange(kmax)[None], T - 1)  # [T, kmax]
    windows = actions[:, index].reshape(E * T, kmax, -1)
    starts = obs[:, :-1].reshape(E * T, -1)
    return np.asarray(_rollouts(step, starts, windows)).reshape(E, T, kmax, -1)


@partial(jax.jit, static_argnums=0)
def _rollouts(step, starts, windows):
    def roll(s, us):
        return jax.lax.scan(lambda s, u: (step(s, u),) * 2, s, us)[1]

    return jax.vmap(roll)(starts, windows)


def multistep_errors(
    step: Callable, obs, actions, ks: Sequence[int], angular: np.ndarray, names: Sequence[str]
) -> dict:
    """{k: {"nrmse": float, "rmse": {name: float}}} for every k in `ks` not longer than the
    episodes (non-finite predictions give inf). The step's states may carry more than the
    named observations (a model's effect states, after them): only the named are scored."""
    obs, actions = np.asarray(obs, np.float32), np.asarray(actions, np.float32)
    T = actions.shape[1]
    ks = sorted({int(k) for k in ks if 1 <= int(k) <= T})
    if not ks:
        return {}
    preds = open_loop_predictions(step, obs, actions, max(ks))[..., : len(names)]
    obs = obs[..., : len(names)]
    scale = obs.reshape(-1, obs.shape[-1]).std(0)
    scale = np.where(scale > 1e-6, scale, 1.0)
    out = {}
    for k in ks:
        pred = preds[:, : T - k + 1, k - 1]  # [E, T-k+1, n]
        err = np.asarray(wrap_angles(jnp.asarray(pred - obs[:, k:]), angular))
        with np.errstate(over="ignore", invalid="ignore"):
            rmse = np.sqrt(np.mean(err.astype(np.float64) ** 2, axis=(0, 1)))
        rmse = np.where(np.isfinite(rmse), rmse, np.inf)
        out[k] = {
            "nrmse": float(np.mean(rmse / scale)),
            "rmse": {n: float(v) for n, v in zip(names, rmse, strict=True)},
        }
    return out


def closed_loop_returns(model, task, act, starts, horizon: int, ctrl_range) -> np.ndarray:
    """[E]: the return of the policy `act` (JAX in, JAX out) run through `model` for `horizon`
    steps from each of `starts` [E, n_obs] (observations; a model with action delays starts
    their buffers at rest), the task's rewards as the simulator scores them."""
    from hds.algo.rollout import perturbed_rollout

    low, high = (jnp.asarray(np.asarray(ctrl_range)[:, i], jnp.float32) for i in (0, 1))
    zeros = jnp.zeros((horizon, len(low)), jnp.float32)

    def episode_return(start):
        start = model.start(start)
        return perturbed_rollout(model, None, task, act, start, zeros, low, high)[2].sum()

    return np.asarray(jax.jit(jax.vmap(episode_return))(jnp.asarray(starts, jnp.float32)))
