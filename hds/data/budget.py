"""What processing recorded data will cost, estimated from its size before it is processed
(issue 41, docs/cli.md "Large data").

Gap discovery holds every k-step window of the data on the device and fits every candidate on
all of them, so its memory and time grow with the recorded steps (episodes x steps); fitting a
learned dynamics model holds every transition and passes over them once an epoch. Every command
that reads or records data for either (hds.discover, hds.run with dynamics.data= or a learned
model or simulator=corrected, hds.loop, hds.dynamics) checks its size here, once, before
anything is processed: data past the work's limit (`discover.max_steps`, `dynamics.max_steps`)
is refused in one line with the memory and time it would need and the fixes.

The costs per step below are measured (experiments/large_data/README.md, the command there
reproduces them) on the team's 2-core AMD EPYC (shared with other work), CPU backend, with the
compilation cache warm; a GPU runs faster, so the times are an upper estimate there.
"""

from __future__ import annotations

from dataclasses import dataclass

from hds.data.format import Dataset


@dataclass(frozen=True)
class Work:
    name: str  # what is done with the data, as the messages say it
    key: str  # the config key of its limit in recorded steps
    bytes_per_step: float  # peak memory per recorded step, beyond a fixed base
    seconds_per_step: float  # wall time per recorded step (per epoch for a model's fit)
    seconds_fixed: float  # compiles and the like, whatever the size

    def seconds(self, steps: int, epochs: int = 1) -> float:
        return self.seconds_fixed + self.seconds_per_step * steps * epochs


# Gap discovery on the cart-pole (`hds.discover.discover`, analytic backend, default settings):
# 2 episodes of a million steps took it to 10.5 GB (issue 41's report), about 5 kB a step; the
# time per step is measured by experiments/large_data/calibrate.py (see its README).
DISCOVERY = Work("gap discovery", "discover.max_steps", 5_000, 4.0e-3, 60.0)
# Fitting an MLP of 2 x 128 units (`hds.dynamics.fit`, minibatch 256): the transitions and
# their targets in float32 with the optimiser's copies are well under 1 kB a step; the time is
# per step and epoch (an early stop ends it sooner), measured as above.
DYNAMICS_FIT = Work("fitting the dynamics model", "dynamics.max_steps", 1_000, 2.0e-5, 20.0)

FILE_FIX = "give it a window of the data (fewer or shorter episodes) or resample it to a coarser dt"


def duration(seconds: float) -> str:
    """`seconds` as a person reads it: 40 s, 12 min, 2.1 h."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def size(nbytes: float) -> str:
    """`nbytes` as a person reads it: 0.5 MB, 120 MB, 10 GB."""
    return f"{nbytes / 1e6:.2g} MB" if nbytes < 1e9 else f"{nbytes / 1e9:.3g} GB"


def estimate(work: Work, steps: int, epochs: int = 1) -> str:
    """What `work` on `steps` recorded steps needs: 'about 1.2 GB of memory and 3 min'."""
    return (
        f"about {size(steps * work.bytes_per_step)} of memory and "
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
    (`fit`, default: whether a run uses a model) and gap discovery (simulator=corrected, the
    loop)."""
    dyn = cfg.dynamics
    works = []
    if (cfg.uses_model() and not dyn.path) if fit is None else fit:  # a saved model: no fit
        works.append((DYNAMICS_FIT, dyn.max_steps, dyn.epochs))
    if cfg.simulator == "corrected" or loop:
        works.append((DISCOVERY, cfg.discover.max_steps, 1))
    if not works:
        return
    if loop:  # the loop's own records; active excitation may add more (checked as it runs)
        per_round = cfg.loop.deploy_episodes + cfg.loop.excitation_episodes
        episodes, horizon = cfg.loop.rounds * per_round, cfg.env.task.horizon
        where = f"the loop's data (loop.rounds = {cfg.loop.rounds} of {per_round} episodes)"
        fix = "lower loop.rounds, loop.deploy_episodes, loop.excitation_episodes or the horizon"
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
        import time

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
