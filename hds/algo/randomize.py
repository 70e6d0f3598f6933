"""Domain randomization (`method=dr`): every rollout runs on the simulator with the parameters of
the effects of `dr.effects` drawn uniformly from their ranges (one draw per rollout, inside the
jitted epoch, from the epoch's key). The simulator's own effects (env.effects) keep their values.

As brax's `randomization_fn`, randomization is an object handed to the trainer
(`make_train_from_config(cfg, env, randomization=randomization(cfg, env))`), not a flag it
reads: the registry of simulator kinds (hds.simulators) builds it for `simulator=randomized`.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp

from hds.effects import EffectSpec, place
from hds.envs import make_env


def _specs(cfg, end):
    """env.effects, then dr.effects with each ranged parameter at `end` of its range
    (0: low, 1: high, 0.5: the middle)."""
    ranged = [
        EffectSpec(e.name, e.target, {k: lo + end * (hi - lo) for k, (lo, hi) in e.ranges.items()})
        for e in cfg.dr.effects
    ]
    return [*cfg.env.effects, *ranged]


def randomized_env(cfg):
    """The simulator with the randomized effects placed, at the middle of their ranges (its
    sim return is taken there)."""
    return make_env(cfg.env, effects=_specs(cfg, 0.5))


def effect_ranges(cfg, env):
    """(low, high): effect parameters aligned with `randomized_env(cfg).params`."""
    low, high = (place(_specs(cfg, end), env.sim.targets)[1] for end in (0, 1))
    return low, high


def sample_effects(key, low, high, count: int):
    """`count` draws of the effect parameters, each uniform in [low, high] (stacked on axis 0);
    a parameter whose range has no width keeps its value exactly."""
    leaves, tree = jax.tree.flatten(low)
    keys = jax.random.split(key, len(leaves))
    draws = [
        lo + (hi - lo) * jax.random.uniform(k, (count, *jnp.shape(lo)))
        for k, lo, hi in zip(keys, leaves, jax.tree.leaves(high))
    ]
    return jax.tree.unflatten(tree, draws)


@dataclass(frozen=True)
class Randomization:
    """Each rollout's effect parameters drawn uniformly in [low, high] (aligned with the env's
    params). The ranges travel in the trainer's hparams (`hparams()`), stacked per run as
    every numeric setting is, so a batch may give each run its own ranges."""

    low: object
    high: object

    def hparams(self) -> dict:
        return {"effect_ranges": (self.low, self.high)}

    def draw(self, key, hparams, count: int):
        """`count` draws of the effect parameters (stacked on axis 0), from hparams' ranges."""
        return sample_effects(key, *hparams["effect_ranges"], count)


def randomization(cfg, env) -> Randomization:
    """The domain randomization of `cfg.dr` on `env` (`randomized_env(cfg)`)."""
    return Randomization(*effect_ranges(cfg, env))
