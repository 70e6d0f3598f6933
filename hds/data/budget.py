"""What processing recorded data will cost, estimated from its size before it is processed
(issue 41, docs/cli.md "Large data").

Gap discovery holds every k-step window of the data on the device and fits every candidate on
all of them, so its memory and time grow with the recorded steps (episodes x steps); fitting a
learned dynamics model holds every transition and passes over them once an epoch. Every command
that reads or records data for either (hds.discover, hds.run with dynamics.data= or a learned
model or simulator=corrected, hds.loop, hds.dynamics) checks its size through `check`,
before anything is processed: data past the work's limit (`discover.max_steps`,
`dynamics.max_steps`) is refused in one line with the memory and time it would need and the
fixes. Within the limit, `Progress` shows long work's stages on the console.

The costs per step below are measured (experiments/large_data/README.md, the command there
reproduces them) on the team's 2-core AMD EPYC under heavy load from other work, CPU backend,
compiles included: an upper estimate on a quiet machine, and on a GPU.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from hds.config import kinds
from hds.data.format import Dataset


@dataclass(frozen=True)
class Work:
    name: str  # what is done with the data, as the messages say it
    key: str  # the config key of its limit in recorded steps
    bytes_fixed: float  # the process's peak memory whatever the size (JAX, the compiles)
    bytes_per_step: float  # peak memory per recorded step beyond it
    seconds_fixed: float  # compiles and the like, whatever the size
    seconds_per_step: float  # wall time per recorded step (per epoch for a model's fit)

    def bytes(self, steps: int) -> float:
        return self.bytes_fixed + self.bytes_per_step * steps

    def seconds(self, steps: int, epochs: int = 1) -> float:
        return self.seconds_fixed + self.seconds_per_step * steps * epochs


# Gap discovery on the cart-pole (`hds.discover.discover`, analytic backend, default settings,
# 8 episodes of 250, 1000 and 4000 steps: 72, 186 and 566 s, peak 0.78, 0.82 and 1.01 GB, at
# a load average of 10 to 17 on the 2 cores): about 16 ms a step after 40 s. Memory: 0.8 GB
# for the process; per step, the measurement at the size that matters, 2 episodes of
# a million steps taking it to 10.5 GB, about 5 kB a step (these small sizes gave 8 kB, their
# peaks dominated by the compiles).
DISCOVERY = Work("gap discovery", "discover.max_steps", 0.8e9, 5_000, 40.0, 1.6e-2)
# Fitting an MLP of 2 x 128 units (`hds.dynamics.fit`, minibatch 256, 10 epochs without an
# early stop, on 8 x 1000 and 8 x 16000 steps: 58 and 85 s, peak 0.73 and 0.81 GB, measured as
# above): 23 us per step and epoch after 56 s, 0.7 kB a step; an early stop ends it sooner.
DYNAMICS_FIT = Work("fitting the dynamics model", "dynamics.max_steps", 0.73e9, 700, 56.0, 2.3e-5)

FILE_FIX = "give it a window of the data (fewer or shorter episodes) or resample it to a coarser dt"


def duration(seconds: float) -> str:
    """`seconds` as a person reads it: 40 s, 12 min, 2.1 h."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def size(nbytes: float) -> str:
    """`nbytes` as a person reads it: 0.5 MB, 120 MB, 10 GB."""
    if nbytes >= 1e9:
        return f"{nbytes / 1e9:.3g} GB"
    return f"{nbytes / 1e6:.0f} MB" if nbytes >= 10e6 else f"{nbytes / 1e6:.2g} MB"


def estimate(work: Work, steps: int, epochs: int = 1) -> str:
    """What `work` on `steps` recorded steps needs: 'about 1.2 GB of memory and 3 min'."""
    return (
        f"about {size(work.bytes(steps))} of memory and "
        f"{duration(work.seconds(steps, epochs))} (a 2-core CPU's time)"
    )


def check(
    work: Work,
    steps: int,
    limit: int,
    where: str,
    shape: str = "",
    fix: str = FILE_FIX,
    epochs: int = 1,
) -> str:
    """Refuse data of `steps` recorded steps past `limit` (the value of work.key) with a
    ValueError naming `where`, the numbers, `fix` and the limit's key; within it, return the
    estimate (for the caller to log as its work starts). `shape`: '(4 episodes x 26)'."""
    needs = estimate(work, steps, epochs)
    if steps > limit:
        raise ValueError(
            f"{where} holds {steps} steps{f' ({shape})' if shape else ''}, more than "
            f"{work.key} = {limit}: {work.name} would need {needs}. {fix[0].upper()}{fix[1:]}, "
            f"or raise {work.key} if the machine has the memory and the time"
        )
    return needs


def check_dataset(work: Work, dataset: Dataset, limit: int, where: str, epochs: int = 1) -> str:
    """`check` on a dataset's recorded steps (episodes x steps)."""
    return check(
        work,
        dataset.n_episodes * dataset.horizon,
        limit,
        where,
        f"{dataset.n_episodes} episodes x {dataset.horizon}",
        epochs=epochs,
    )


def check_planned(cfg, loop: bool = False, fit: bool | None = None) -> None:
    """Every `check` a run's config implies, before anything is recorded or compiled: on the
    dataset `dynamics.data` (read for its size), or on the data the command records on its
    plant (dynamics.episodes x dynamics.horizon; hds.loop: every round's deployed and
    excitation episodes, at least), for each work it does with them: a learned model's fit
    (`fit`, default: whether a run uses a model) and gap discovery (a simulator kind that
    `discovers`: simulator=corrected; the loop)."""
    dyn = cfg.dynamics
    works = []
    if (cfg.uses_model() and not dyn.path) if fit is None else fit:  # a saved model: no fit
        works.append((DYNAMICS_FIT, dyn.max_steps, dyn.epochs))
    if kinds.kind(cfg.simulator).discovers or loop:
        works.append((DISCOVERY, cfg.discover.max_steps, 1))
    if not works:
        return
    if loop:  # the loop's own records; active excitation may add more (checked as it runs)
        per_round = cfg.loop.deploy_episodes + cfg.loop.excitation_episodes
        episodes, horizon = cfg.loop.rounds * per_round, cfg.env.task.horizon
        where = f"the loop's data (loop.rounds = {cfg.loop.rounds}, {per_round} episodes each)"
        fix = (
            "lower loop.rounds, loop.deploy_episodes, loop.excitation_episodes or env.task.horizon"
        )
    elif dyn.data:
        from hds.data.format import load

        dataset = load(dyn.data)
        episodes, horizon = dataset.n_episodes, dataset.horizon
        where, fix = f"dynamics.data = {dyn.data}", FILE_FIX
    else:
        episodes, horizon = dyn.episodes, dyn.horizon
        where = "the data recorded on the plant (dynamics.episodes x dynamics.horizon)"
        fix = "lower dynamics.episodes or dynamics.horizon"
    for work, limit, epochs in works:
        check(
            work, episodes * horizon, limit, where, f"{episodes} episodes x {horizon}", fix, epochs
        )


class Progress:
    """Progress of long work on the console: each stage as it ends, with the time so far
    against the estimate (`work` on `steps`), so that minutes of work never show nothing."""

    def __init__(self, work: Work, steps: int, log, epochs: int = 1):
        self.work, self.log, self.clock = work, log, time.perf_counter
        self.start, self.expected = self.clock(), work.seconds(steps, epochs)
        log.info("%s on %d recorded steps: %s", work.name, steps, estimate(work, steps, epochs))

    def __call__(self, stage: str) -> None:
        self.log.info(
            "%s: %s (%s so far, about %s expected)",
            self.work.name,
            stage,
            duration(self.clock() - self.start),
            duration(self.expected),
        )
