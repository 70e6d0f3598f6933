"""Record a Dataset from any plant (hds.real): a policy or an open-loop signal, run with
`hds.real.rollout`, with the names and dt taken from the plant.

The recorded action is the control applied, i.e. saturated to the plant's ctrl_range (as
`hds.real.rollout` records it); excitation signals from `hds.data.excitation` already lie within
the limits.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import numpy as np

from hds.data.format import Dataset
from hds.real import rollout


def initial_states(task, seed, n_episodes: int) -> tuple[np.ndarray, np.ndarray]:
    """n_episodes initial states (q0 [E, nq], qd0 [E, nv]) drawn from the task's distribution;
    `seed` is an int or a JAX PRNG key."""
    key = jax.random.PRNGKey(seed) if isinstance(seed, int | np.integer) else seed
    q0, qd0 = jax.vmap(task.initial)(jax.random.split(key, n_episodes))
    return np.asarray(q0, dtype=np.float64), np.asarray(qd0, dtype=np.float64)


def collect(
    plant, task, q0, qd0, controller: Callable | np.ndarray, horizon: int | None = None
) -> Dataset:
    """Run E episodes on `plant` from (q0 [E, nq], qd0 [E, nv]) and record them.

    `controller` is a policy obs [E, n_obs] -> u [E, n_act], or open-loop controls
    [E, T, n_act] (e.g. an excitation signal), for which `horizon` defaults to T.
    `task` only scores the rollout (rewards are not part of a Dataset)."""
    q0, qd0 = np.asarray(q0), np.asarray(qd0)
    if q0.ndim != 2 or qd0.ndim != 2 or len(q0) != len(qd0):
        raise ValueError(
            f"q0 {q0.shape} and qd0 {qd0.shape} must be [E, nq] and [E, nv] for the same E episodes"
        )
    n_act = len(plant.action_names)
    if not callable(controller):
        controller = np.asarray(controller, dtype=np.float64)
        expected = (len(q0), controller.shape[1] if controller.ndim == 3 else "T", n_act)
        if controller.ndim != 3 or controller.shape[0] != len(q0) or controller.shape[2] != n_act:
            raise ValueError(
                f"open-loop controls have shape {controller.shape}; this plant and "
                f"these initial states need [E, T, n_act] = {list(expected)}"
            )
        horizon = controller.shape[1] if horizon is None else horizon
        if horizon > controller.shape[1]:
            raise ValueError(
                f"horizon = {horizon} is longer than the {controller.shape[1]} "
                "steps of the open-loop controls"
            )
    elif horizon is None:
        raise ValueError("give the horizon (steps per episode) when the controller is a policy")
    if int(horizon) < 1:
        raise ValueError(f"horizon = {horizon} must be at least 1 step")
    episodes = rollout(plant, task, q0, qd0, controller, int(horizon))
    return Dataset(
        episodes.obs,
        episodes.actions,
        float(plant.dt),
        tuple(plant.obs_names),
        tuple(plant.action_names),
    )
