""" "Real" plants: black boxes to reset, step, roll a policy out on and record data from.

Every plant works on a batch of B episodes with NumPy arrays and exposes:
  obs_names, action_names, dt, ctrl_range [n_act, 2]
  reset(q [B, nq], qd [B, nv]) -> obs [B, n_obs]     the measured observation
  step(u [B, n_act]) -> obs [B, n_obs]
  state() -> (q, qd)                                  the true state, for rewards
  noise_state() -> dict, set_noise_state(dict)        where its measurement noise stands
      (JSON-ready): a run that resumes past recordings it skips restores it, so that it
      measures the noise an uninterrupted run measures
No gradient is ever taken through a plant.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import jax
import numpy as np

from hds.envs import make_env


@dataclass
class Episodes:
    obs: np.ndarray  # [B, T+1, n_obs]
    actions: np.ndarray  # [B, T, n_act]
    rewards: np.ndarray  # [B, T]

    @property
    def returns(self) -> np.ndarray:
        return self.rewards.sum(axis=1)


def rollout(plant, task, q0, qd0, controller: Callable | np.ndarray, horizon: int) -> Episodes:
    """Run B episodes on a plant. `controller` is a function obs [B, n_obs] -> u [B, n_act]
    (a policy) or an array of open-loop controls [B, T, n_act]. The recorded actions are the
    controls applied, i.e. saturated to the actuators' range. Rewards come from the true state."""
    reward = _batched_reward(task)
    obs = [plant.reset(np.asarray(q0), np.asarray(qd0))]
    actions, rewards = [], []
    low, high = plant.ctrl_range[:, 0], plant.ctrl_range[:, 1]
    for t in range(horizon):
        u = controller(obs[-1]) if callable(controller) else np.asarray(controller)[:, t]
        u = np.clip(np.asarray(u, dtype=np.float64), low, high)
        obs.append(plant.step(u))
        q, qd = plant.state()
        actions.append(u)
        rewards.append(np.asarray(reward(q, qd, u)))
    return Episodes(np.stack(obs, 1), np.stack(actions, 1), np.stack(rewards, 1))


_REWARDS: dict = {}


def _batched_reward(task):
    if id(task) not in _REWARDS:  # compile once per task
        _REWARDS[id(task)] = (task, jax.jit(jax.vmap(task.reward)))
    return _REWARDS[id(task)][1]


def make_plant(real_cfg, env_cfg):
    """The plant of a `real` config, for the system of an `env` config."""
    effects = list(real_cfg.effects)
    if real_cfg.plant == "brax":
        from hds.real.brax_plant import BraxPlant

        return BraxPlant(
            make_env(env_cfg, effects=effects, sharpness=None, friction_gap=real_cfg.friction_gap)
        )
    from hds.real.mujoco_plant import MujocoPlant

    return MujocoPlant(env_cfg, effects, friction_gap=real_cfg.friction_gap)


__all__ = ["Episodes", "make_plant", "rollout"]
