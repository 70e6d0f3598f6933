"""The policy regression's shuffles are jax.random.permutation's own, and its early stop skips
what a plain loop over the inner epochs skips: the cheaper program computes the same numbers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from hds.algo.regress import regress, weighted_mse
from hds.utils.shuffle import permutation, stable_argsort


@pytest.mark.parametrize("n", [1, 2, 37, 5000])
def test_permutation_is_jax_random_permutation(n):
    keys = jax.random.split(jax.random.PRNGKey(3), 8)
    ours = jax.jit(jax.vmap(lambda k: permutation(k, n)))(keys)
    theirs = jax.vmap(lambda k: jax.random.permutation(k, n))(keys)
    np.testing.assert_array_equal(ours, theirs)
    one = jax.jit(lambda k: permutation(k, n))(keys[0])  # unbatched: a while loop of its own
    np.testing.assert_array_equal(one, theirs[0])


def test_stable_argsort_orders_equal_keys_by_index():
    rng = np.random.default_rng(0)
    argsort = jax.jit(stable_argsort)
    for size in (1, 9, 64):  # one padded shape per size; keys from 0..3 tie a lot
        for _ in range(20):
            keys = rng.integers(0, 4, size).astype(np.uint32)
            np.testing.assert_array_equal(argsort(keys), np.argsort(keys, kind="stable"))


def plain_regress(apply, optimizer, params, opt_state, obs, targets, key, inner_epochs, size, tol):
    """The regression as a Python loop: shuffle, minibatch steps, loss; stop once an inner
    epoch lowers the loss by less than tol."""
    loss_of = jax.jit(lambda p, o, t: weighted_mse(apply, p, o, t, jnp.ones(o.shape[0])))

    @jax.jit
    def step(params, opt_state, o, t):
        updates, opt_state = optimizer.update(jax.grad(loss_of)(params, o, t), opt_state, params)
        return optax.apply_updates(params, updates), opt_state

    loss, n, ran = loss_of(params, obs, targets), obs.shape[0], 0
    for k in jax.random.split(key, inner_epochs):
        order = np.asarray(jax.random.permutation(k, n)[: n // size * size]).reshape(-1, size)
        for rows in order:
            params, opt_state = step(params, opt_state, obs[rows], targets[rows])
        new_loss, ran = loss_of(params, obs, targets), ran + 1
        stop = loss - new_loss < tol
        loss = new_loss
        if stop:
            break
    return params, loss, ran


@pytest.mark.parametrize("tol", [-np.inf, 0.02])
def test_regress_matches_a_plain_loop(tol):
    def apply(p, o):
        return jnp.tanh(o @ p["w"]) @ p["v"]

    key = jax.random.PRNGKey(0)
    obs = jax.random.normal(key, (70, 3))
    targets = jnp.sin(obs[:, :1] * 2.0)
    params = {"w": jax.random.normal(jax.random.PRNGKey(1), (3, 8)), "v": jnp.zeros((8, 1))}
    optimizer = optax.adam(3e-2)
    args = (apply, optimizer, params, optimizer.init(params), obs, targets)
    expected, expected_loss, ran = plain_regress(*args, key, 12, 16, tol)
    assert (ran == 12) == (tol == -np.inf)  # the early stop is exercised, and the full run too
    got, _, loss = jax.jit(
        lambda *a: regress(*a, inner_epochs=12, minibatch=16, tol=tol), static_argnums=(0, 1)
    )(*args[:4], obs, targets, jnp.ones(70), key)
    np.testing.assert_allclose(loss, expected_loss, rtol=1e-5)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(expected)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)
