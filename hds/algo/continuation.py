"""The continuation: what a run changes besides the policy, epoch by epoch, as one object.

  effect ramp   the simulator's effects (and a learned model's share of the rollouts) grow
                from nothing to their values over [begin, end] epochs
  wait          the ramp starts only once the policy has solved the task `solved_for` epochs
                in a row (at the latest so that it still ends on the last epoch)
  pauses        once under way, the ramp stands still after every epoch the policy fails
  keep-best     the policy with the best training return once the ramp has ended
  horizon       the action improvement counts a horizon growing from `horizon_start` steps

It works as an optax transformation does, on a state of one fixed structure for every
setting (a checkpoint's arrays do not depend on the configuration):

    continuation = Continuation(epochs=150, ramp=(75, 105), solved_at=-40.0, keep_best=True)
    progress = continuation.init(policy_params)
    point = continuation.at(progress, epoch)            # the ramp's share, the counted steps
    params = ramp_effects(params, sites, point.share)   # the simulator's effects at that share
    ...                                                 # one epoch of training
    progress = continuation.update(progress, epoch, point, policy_params, sim_return)
    policy = continuation.final_policy(progress, policy_params)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from hds.effects.library import effect_type
from hds.utils.pytree import pytree_dataclass


@pytree_dataclass
class Progress:
    """What the continuation carries across epochs (each field exists in every setting; the
    ones a setting does not use keep their initial values)."""

    # the epoch the policy had solved the task `solved_for` epochs in a row (epochs: not yet)
    solved: jax.Array
    streak: jax.Array  # the epochs in a row it has solved it now
    paused: jax.Array  # the epochs the ramp stood still (pauses)
    best: Any  # the kept policy (keep_best)
    best_return: jax.Array  # its training return; -inf: none kept yet


class Point(NamedTuple):
    """Where the continuation stands at an epoch."""

    share: jax.Array  # how far the effect ramp has gone: 0 before it, 1 at its end
    counted: jax.Array | None  # [horizon] weights of the steps the improvement counts; None: all


@dataclass(frozen=True)
class Continuation:
    epochs: int
    ramp: tuple[float, float] = (0.0, 0.0)  # [begin, end] epochs of the effect ramp; (0, 0): none
    solved_at: float | None = None  # the ramp waits for a training return >= this; None: no wait
    solved_for: int = 1  # ... in this many epochs in a row
    pauses: bool = False  # the ramp stands still after each epoch that misses solved_at
    keep_best: bool = False
    horizon: int = 0  # the task's whole horizon
    horizon_start: int = 0  # the steps counted at the first epoch (0: the whole horizon)
    horizon_full_at: float = 0.0  # the epoch from which the whole horizon counts

    @property
    def ramped(self) -> bool:
        return bool(self.ramp[1])

    @property
    def waits(self) -> bool:
        return self.ramped and self.solved_at is not None

    def init(self, policy) -> Progress:
        return Progress(
            solved=jnp.array(self.epochs, jnp.int32),  # not yet
            streak=jnp.array(0, jnp.int32),
            paused=jnp.array(0, jnp.int32),
            best=policy,
            best_return=jnp.float32(-jnp.inf),
        )

    def at(self, progress: Progress, epoch) -> Point:
        return Point(ramp_share(epoch, *self.ramp, self.delay(progress)), self.counted(epoch))

    def counted(self, epoch):
        """The horizon curriculum's weights of a rollout's steps at `epoch` ([horizon], 1 or
        0); None: all of them."""
        return counted_steps(epoch, self.horizon_start, self.horizon_full_at, self.horizon)

    def delay(self, progress: Progress):
        """Epochs the ramp waits for the policy to solve the task: until the epoch after it
        first did so `solved_for` epochs in a row, plus (pauses) each epoch on the ramp it
        failed, at most until the ramp ends on the last epoch."""
        if not self.waits:
            return 0
        waited = progress.solved + 1 - self.ramp[0]
        waited = waited + (progress.paused if self.pauses else 0)
        return jnp.clip(waited, 0, self.epochs - self.ramp[1])

    def update(self, progress: Progress, epoch, point: Point, policy, sim_return) -> Progress:
        """The next epoch's progress, after `policy` (the one this epoch trained from) had the
        training return `sim_return` on the simulator at `point`."""
        if self.waits:
            progress = self._count_solved(progress, epoch, point.share, sim_return)
        if self.keep_best:  # among the epochs with the continuation at its end
            better = (point.share >= 1) & (sim_return > progress.best_return)
            progress = progress.replace(
                best_return=jnp.where(better, sim_return, progress.best_return),
                best=jax.tree.map(lambda k, now: jnp.where(better, now, k), progress.best, policy),
            )
        return progress

    def _count_solved(self, progress: Progress, epoch, share, sim_return) -> Progress:
        solved_now = sim_return >= self.solved_at
        streak = jnp.where(solved_now, progress.streak + 1, 0)
        first = (progress.solved == self.epochs) & (streak >= self.solved_for)
        paused = progress.paused
        if self.pauses:
            failed = (share > 0) & (share < 1) & ~solved_now
            paused = paused + failed.astype(jnp.int32)
        solved = jnp.where(first, epoch, progress.solved)
        return progress.replace(solved=solved, streak=streak, paused=paused)

    def final_policy(self, progress: Progress, policy):
        """The policy a run returns: the kept one (keep_best, once one was kept), else the
        last; `progress` and `policy` may hold a batch of runs on axis 0."""
        if not self.keep_best:
            return policy
        return kept_or_last(progress.best, progress.best_return, policy)


def kept_or_last(best, best_return, policy):
    """Each run's kept policy `best` where one was kept (`best_return` above -inf), else its
    last `policy`; one run, or a batch of runs on axis 0."""
    found = jnp.asarray(best_return) > -jnp.inf  # [] or one per run of a batch

    def pick(kept, last):
        where = found.reshape(found.shape + (1,) * (jnp.ndim(kept) - found.ndim))
        return jnp.where(where, kept, last)

    return jax.tree.map(pick, best, policy)


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


def ramp_effects(params, sites, share):
    """The effects' parameters `share` of the way from their nominal values (the effect does
    nothing) to their own; a discrete parameter (a delay's length) sets a shape and is at its
    own value throughout. A policy first learned without the effect is a starting point from
    which the gradient still flows, where dry friction at full strength from the start holds
    the cart still and leaves the policy little to learn from."""
    nominal = [
        {k: effect_type(site.name).param(k).nominal for k in values}
        for site, values in zip(sites, params)
    ]
    # an infinite nominal (a saturation's limit) has no line to the value: the value throughout
    return tuple(
        {k: n[k] + share * (v - n[k]) if math.isfinite(n[k]) else v for k, v in values.items()}
        for n, values in zip(nominal, params)
    )


def effect_ramp(params, sites, epoch, begin: float, end: float, delay=0):
    """The effects' parameters at `epoch` of a ramp over [begin, end] epochs (+ `delay`):
    nominal until `begin`, their own from `end` (begin = end = 0: their own from the start)."""
    if not end:
        return params
    return ramp_effects(params, sites, ramp_share(epoch, begin, end, delay))
