"""Acquiring data on a plant: episodes of open-loop excitation, a policy deployed beside them
(the loop's rounds), and active excitation, which records more at doubled amplitude while the
data so far cannot identify what more excitation would.

What lies above the data (the excitation signal or its design, the identifiability check of
gap discovery) is passed in as functions, so this module imports nothing above hds/data. The
corrected simulator (hds.simulators), the model's data (hds.dynamics) and the loop (hds.loop)
all record through here.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence

import jax
import numpy as np

from hds.data.collect import collect, initial_states
from hds.data.format import Dataset, concatenate

# controls(key, q0, qd0, deployed) -> open-loop controls [E, T, n_act] for the episodes that
# start at (q0, qd0); `deployed`: what the policy recorded before them (None: no policy)
Controls = Callable[..., np.ndarray]


def excited(plant, task, key, episodes: int, horizon: int, controls: Controls) -> Dataset:
    """`episodes` of open-loop `controls` on `plant` from the task's initial states."""
    k_init, k_u = jax.random.split(key)
    q0, qd0 = initial_states(task, k_init, episodes)
    return collect(plant, task, q0, qd0, controls(k_u, q0, qd0, None), horizon)


def deployed_and_excited(
    plant, task, key, act, deploy_episodes: int, episodes: int, horizon: int, controls: Controls
) -> Dataset:
    """A round's data: the policy `act` (obs -> u) deployed for `deploy_episodes` from the
    task's initial states, then `episodes` of open-loop `controls` from others."""
    k_deploy, k_excite, k_u = jax.random.split(key, 3)
    q0, qd0 = initial_states(task, k_deploy, deploy_episodes)
    deployed = collect(plant, task, q0, qd0, act, horizon)
    q0, qd0 = initial_states(task, k_excite, episodes)
    excitation = collect(plant, task, q0, qd0, controls(k_u, q0, qd0, deployed), horizon)
    return concatenate([deployed, excitation])


def until_identifiable(
    record: Callable[[float, int], Dataset],
    unidentified: Callable[[Dataset], Sequence[str]],
    scale: float,
    data_so_far=(),
):
    """Active excitation: record with `record(scale, attempt) -> Dataset` (its excitation's
    amplitude `scale` of the actuators' half range); while `unidentified(all data so far)`
    names what more excitation would identify, double the amplitude, up to the whole range,
    and record again. Returns (every dataset so far, the last amplitude, notes saying what was
    done and why)."""
    data, notes = list(data_so_far), []
    for attempt in itertools.count():
        data.append(record(scale, attempt))
        reasons = sorted(set(unidentified(concatenate(data))))
        if not reasons or scale >= 1.0:
            notes += [f"still not identifiable at full excitation: {r}" for r in reasons]
            return data, scale, notes
        notes.append(
            f"{'; '.join(reasons)} (excitation {scale:g} of the half range): recorded more at "
            f"{min(1.0, 2 * scale):g}"
        )
        scale = min(1.0, 2 * scale)
