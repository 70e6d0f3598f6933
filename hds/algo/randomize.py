"""Domain randomization (`method=dr`): every rollout runs on the simulator with the parameters of
the effects of `dr.effects` drawn uniformly from their ranges (one draw per rollout, inside the
jitted epoch, from the epoch's key). The simulator's own effects (env.effects) keep their values.
"""

from __future__ import annotations

from typing import NamedTuple

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


class Randomization(NamedTuple):
    """Domain randomization as a trainer's part: every simulator rollout draws its effect
    parameters from `ranges` ((low, high), as `effect_ranges` gives them; the trainer's
    hparams["effect_ranges"], so they may be swept)."""

    ranges: tuple

    def hparams(self) -> dict:
        return {"effect_ranges": self.ranges}

    def draw(self, key, hparams, count: int):
        return sample_effects(key, *hparams["effect_ranges"], count)
