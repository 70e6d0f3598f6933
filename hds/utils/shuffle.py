"""`jax.random.permutation(key, n)`, the same permutation at a quarter of its cost on a CPU.

jax shuffles by stable key-value sorts of random 32-bit keys, and XLA's CPU sort of key-value
pairs costs about seven times its sort of the keys alone: on a 2-core CPU the shuffles of the
policy regression's minibatches (20 a training epoch, 5,000 rows) took half of the epoch. Here
each sort is the keys' sort alone, each key's place in it found by binary search.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def stable_argsort(keys: jax.Array) -> jax.Array:
    """`jnp.argsort(keys, stable=True)` of a 1-D array. A key's binary-search place among the
    sorted keys is its rank when it is unique; equal keys (rare among random 32-bit ones) take
    the places after it one at a time, in the order of their indices."""
    n = keys.shape[0]
    index = jnp.arange(n, dtype=jnp.int32)
    first_place = jnp.searchsorted(jax.lax.sort(keys), keys).astype(jnp.int32)

    def place_next_of_each_key(carry):
        taken, place, waiting = carry
        first = (
            jnp.full(n, n, jnp.int32).at[jnp.where(waiting, first_place, n)].min(index, mode="drop")
        )
        now = waiting & (first[first_place] == index)
        return taken + 1, jnp.where(now, first_place + taken, place), waiting & ~now

    _, place, _ = jax.lax.while_loop(
        lambda carry: jnp.any(carry[2]),
        place_next_of_each_key,
        (0, first_place, jnp.ones(n, bool)),
    )
    return jnp.zeros(n, jnp.int32).at[place].set(index, unique_indices=True)


def permutation(key: jax.Array, n: int) -> jax.Array:
    """`jax.random.permutation(key, n)`: its rounds of sorts by fresh random keys (enough
    rounds that all n elements' keys are distinct in one of them, with high probability),
    each key drawn as jax draws it (tests/test_regress.py checks that the two agree)."""
    rounds = int(np.ceil(3 * np.log(max(1, n)) / np.log(np.iinfo(np.uint32).max)))

    def sort_round(carry, _):
        key, order = carry
        key, subkey = jax.random.split(key)
        return (key, order[stable_argsort(jax.random.bits(subkey, (n,), jnp.uint32))]), None

    # the rounds as one traced body, not unrolled copies of the sort (two at n = 5,000): the
    # same integers, one copy of the sort in the program (issue 43)
    return jax.lax.scan(sort_round, (key, jnp.arange(n)), None, length=rounds)[0][1]
