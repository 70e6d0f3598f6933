"""Networks: the policy (observation -> control within the actuator's range)."""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax.numpy as jnp
import numpy as np


def features(obs: jnp.ndarray, angular: np.ndarray) -> jnp.ndarray:
    """Hinge angles enter as (sin, cos), so a policy sees one pole whatever its turn count."""
    nq = len(angular)
    q, rest = obs[..., :nq], obs[..., nq:]
    angles = q[..., angular]
    return jnp.concatenate([q[..., ~angular], jnp.sin(angles), jnp.cos(angles), rest], axis=-1)


class Policy(nn.Module):
    """MLP whose tanh output is scaled onto [low, high] of each actuator."""

    hidden: Sequence[int]
    angular: np.ndarray
    low: np.ndarray
    high: np.ndarray

    @nn.compact
    def __call__(self, obs):
        x = features(obs, self.angular)
        for width in self.hidden:
            x = nn.tanh(nn.Dense(width)(x))
        x = nn.Dense(
            len(self.low), kernel_init=nn.initializers.variance_scaling(0.01, "fan_in", "uniform")
        )(x)
        mid, half = (self.high + self.low) / 2, (self.high - self.low) / 2
        return mid + half * jnp.tanh(x)


def make_policy(hidden: Sequence[int], sim) -> Policy:
    low, high = sim.ctrl_range[:, 0], sim.ctrl_range[:, 1]
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
        raise ValueError(
            "every actuator needs a finite ctrlrange for the policy's output; set "
            "ctrllimited and ctrlrange on each actuator of the MJCF"
        )
    return Policy(tuple(hidden), np.asarray(sim.angular), low, high)
