"""Step-size rules of the action update (`conf/anneal`): which candidate step is taken.

  line_search  the best of alpha / 2^k, only if it improves the return (never a worse sequence)
  simulated    the best candidate; a worse one is still taken with probability
               exp(relative change / temperature), the temperature cooling every epoch
  fixed        always the step alpha (unless it is not finite)
The base step size decays by `step_decay` every epoch in all three. What else changes over a
run (the effects' ramp, the horizon curriculum, keep-best) is the continuation's:
hds/algo/continuation.py.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def accept(kind: str, new, old, temperature, key):
    finite = jnp.isfinite(new)
    if kind == "fixed":
        return finite
    better = finite & (new > old)
    if kind == "line_search":
        return better
    relative = (new - old) / (jnp.abs(old) + 1e-8)
    chance = jnp.exp(relative / jnp.maximum(temperature, 1e-12))
    return better | (finite & (jax.random.uniform(key) < chance))


def step_size(base, decay: float, epoch):
    return base * decay**epoch


def temperature(initial: float, cooling: float, epoch):
    return initial * cooling**epoch


def candidates(kind: str, line_search: int) -> int:
    """How many step sizes alpha / 2^k are tried together."""
    return 1 if kind == "fixed" else line_search
