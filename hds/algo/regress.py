"""Regress the policy onto the improved actions (PODS, step 3): supervised MSE, minibatch Adam.

Inner epochs and minibatches are nested `lax.scan`s. Early stopping is a mask: once an inner
epoch lowers the loss by less than `tol`, the remaining updates leave the parameters as they are,
so the compiled program has one shape whatever happens.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax


def weighted_mse(apply, params, obs, targets, weights):
    err = jnp.sum((apply(params, obs) - targets) ** 2, axis=-1)
    return jnp.sum(weights * err) / jnp.maximum(jnp.sum(weights), 1.0)


def regress(
    apply,
    optimizer,
    params,
    opt_state,
    obs,
    targets,
    weights,
    key,
    *,
    inner_epochs: int,
    minibatch: int,
    tol: float,
):
    """Returns (params, opt_state, final loss). Rows with non-finite data get zero weight."""
    finite = jnp.all(jnp.isfinite(obs), -1) & jnp.all(jnp.isfinite(targets), -1)
    weights = jnp.where(finite, weights, 0.0)
    obs, targets = jnp.where(finite[:, None], obs, 0.0), jnp.where(finite[:, None], targets, 0.0)
    n = obs.shape[0]
    size = min(minibatch, n)
    batches = n // size
    loss_of = lambda p, i: weighted_mse(apply, p, obs[i], targets[i], weights[i])  # noqa: E731

    def minibatch_step(carry, idx):
        params, opt_state, stopped = carry
        grads = jax.grad(loss_of)(params, idx)
        updates, new_state = optimizer.update(grads, opt_state, params)
        keep = lambda old, new: jnp.where(stopped, old, new)  # noqa: E731
        params = jax.tree.map(keep, params, optax.apply_updates(params, updates))
        return (params, jax.tree.map(keep, opt_state, new_state), stopped), None

    def epoch(carry, key):
        params, opt_state, loss, stopped = carry
        order = jax.random.permutation(key, n)[: batches * size].reshape(batches, size)
        (params, opt_state, _), _ = jax.lax.scan(
            minibatch_step, (params, opt_state, stopped), order
        )
        new_loss = weighted_mse(apply, params, obs, targets, weights)
        stopped = stopped | (loss - new_loss < tol)
        return (params, opt_state, new_loss, stopped), None

    start = (
        params,
        opt_state,
        weighted_mse(apply, params, obs, targets, weights),
        jnp.array(False),
    )
    (params, opt_state, loss, _), _ = jax.lax.scan(
        epoch, start, jax.random.split(key, inner_epochs)
    )
    return params, opt_state, loss
