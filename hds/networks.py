"""Networks: the policy (observation -> control within the actuator's range)."""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np


def features(obs: jnp.ndarray, angular: np.ndarray) -> jnp.ndarray:
    """Hinge angles enter as (sin, cos), so a policy sees one pole whatever its turn count."""
    nq = len(angular)
    q, rest = obs[..., :nq], obs[..., nq:]
    angles = q[..., angular]
    return jnp.concatenate([q[..., ~angular], jnp.sin(angles), jnp.cos(angles), rest], axis=-1)


@dataclass(frozen=True, eq=False)
class Policy:
    """MLP whose tanh output is scaled onto [low, high] of each actuator: `init` and `apply`
    are those of its flax module (`module`), which is made on first use. A process whose
    programs come from the program cache never calls them, so it never imports flax.linen
    (~0.15 s of a second process). Its content, for the program cache's key, is its fields."""

    hidden: Sequence[int]
    angular: np.ndarray
    low: np.ndarray
    high: np.ndarray

    @functools.cached_property  # beside the fields: the content does not change
    def module(self):
        """The flax module (flax.linen) of this network."""
        return _mlp_class()(tuple(self.hidden), self.angular, self.low, self.high)

    def init(self, *args, **kwargs):
        return self.module.init(*args, **kwargs)

    def apply(self, *args, **kwargs):
        return self.module.apply(*args, **kwargs)


@functools.cache
def _mlp_class():
    """The flax module's class, defined on first use (flax.linen is imported here)."""
    import flax.linen as nn

    class MLP(nn.Module):
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
                len(self.low),
                kernel_init=nn.initializers.variance_scaling(0.01, "fan_in", "uniform"),
            )(x)
            mid, half = (self.high + self.low) / 2, (self.high - self.low) / 2
            return mid + half * jnp.tanh(x)

    return MLP


def make_policy(hidden: Sequence[int], sim) -> Policy:
    low, high = sim.ctrl_range[:, 0], sim.ctrl_range[:, 1]
    if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
        raise ValueError(
            "every actuator needs a finite ctrlrange for the policy's output; set "
            "ctrllimited and ctrlrange on each actuator of the MJCF"
        )
    return Policy(tuple(hidden), np.asarray(sim.angular), low, high)
