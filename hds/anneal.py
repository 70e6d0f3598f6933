"""Step-size rules of the action update (`conf/anneal`): which candidate step is taken.

  line_search  the best of alpha / 2^k, only if it improves the return (never a worse sequence)
  simulated    the best candidate; a worse one is still taken with probability
               exp(relative change / temperature), the temperature cooling every epoch
  fixed        always the step alpha (unless it is not finite)
The base step size decays by `step_decay` every epoch in all three. `effect_ramp` grows the
simulator's effects from nothing to their values over a span of epochs (a continuation), and
with them the share of rollouts through a learned model of the plant (HDS). `counted_steps`
grows the steps the improvement sees (a curriculum).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from hds.effects.library import effect_type


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


def counted_steps(epoch, start: int, full_at: float, whole: int):
    """Which of each rollout's `whole` steps the action improvement counts at `epoch` ([whole]
    weights, 1 or 0): the first `start` at the first epoch, growing linearly to all of them at
    epoch `full_at`; None (all of them, no mask) when `start` is 0 or not below `whole`."""
    if not start or start >= whole:
        return None
    share = jnp.clip(epoch / max(full_at, 1.0), 0.0, 1.0)
    horizon = jnp.round(start + share * (whole - start))
    return (jnp.arange(whole) < horizon).astype(jnp.float32)


def ramp_share(epoch, begin: float, end: float, delay=0):
    """How far the continuation has gone at `epoch`: 0 until epoch `begin` (+ `delay`, which
    may be traced), then linearly to 1 at epoch `end` (+ `delay`); begin = end = 0: 1 from the
    start."""
    if not end:
        return jnp.float32(1.0)
    return jnp.clip((epoch + 1 - begin - delay) / max(end - begin, 1.0), 0.0, 1.0)


def effect_ramp(params, sites, epoch, begin: float, end: float, delay=0):
    """A continuation: the effects' parameters stay at their nominal values (the effect does
    nothing) until epoch `begin`, then move linearly to their own, reached at epoch `end`
    (begin = end = 0: their own from the start); a discrete parameter (a delay's length)
    sets a shape and is at its own value throughout. A policy first learned without the effect
    is a starting point from which the gradient still flows, where dry friction at full
    strength from the start holds the cart still and leaves the policy little to learn from."""
    if not end:
        return params
    share = ramp_share(epoch, begin, end, delay)
    nominal = [
        {k: effect_type(site.name).param(k).nominal for k in values}
        for site, values in zip(sites, params)
    ]
    # an infinite nominal (a saturation's limit) has no line to the value: the value throughout
    return tuple(
        {k: n[k] + share * (v - n[k]) if math.isfinite(n[k]) else v for k, v in values.items()}
        for n, values in zip(nominal, params)
    )
