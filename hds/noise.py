"""Exploration noise on the policy's actions while collecting rollouts (`conf/noise`).

The standard deviation at each epoch, from optax's schedules:
  none         0
  exponential  scale * decay^epoch (the reference project's schedule)
  linear       scale -> final over the run
  cosine       scale -> final over the run, along a half cosine
"""

from __future__ import annotations

import jax.numpy as jnp
import optax


def schedule(cfg, epochs: int, scale, decay):
    """sigma(epoch); `scale` and `decay` may be traced values, so noise sweeps can be vmapped
    (optax's exponential_decay inspects its rate in Python, so that one is written out)."""
    if cfg.schedule == "none":
        return lambda epoch: jnp.zeros(())
    if cfg.schedule == "exponential":
        return lambda epoch: scale * decay**epoch
    if cfg.schedule == "linear":
        return optax.linear_schedule(scale, cfg.final, transition_steps=max(epochs - 1, 1))
    return lambda epoch: (
        cfg.final
        + (scale - cfg.final)
        * optax.cosine_decay_schedule(1.0, decay_steps=max(epochs - 1, 1))(epoch)
    )
