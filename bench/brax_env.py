"""The project's env as a `brax.envs.base.Env`, so brax's own trainers (PPO, APG) run on exactly
the task PODS and HDS train on.

  reset(rng)          the task's initial-state distribution (hds Env.reset)
  step(state, a)      a in [-1, 1]^n_act (brax's tanh policies) is mapped onto the actuator's
                      ctrl range, u = mid + half * a; the reward is the project's
                      task.reward(q, qd, u) of the state reached
  obs                 the policy features PODS's network sees (hinge angles as sin and cos)
  done                never: a fixed horizon; brax's EpisodeWrapper ends episodes at
                      `episode_length`, which the benchmark sets to the task's horizon
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env as BraxEnv
from brax.envs.base import State

from hds.networks import features


class ProjectEnv(BraxEnv):
    def __init__(self, env):
        self.env = env
        low, high = env.sim.ctrl_range[:, 0], env.sim.ctrl_range[:, 1]
        self.mid = jnp.asarray((high + low) / 2)
        self.half = jnp.asarray((high - low) / 2)
        self.angular = np.asarray(env.sim.angular)

    def control(self, action: jax.Array) -> jax.Array:
        """The actuator command of a brax action in [-1, 1]."""
        return self.mid + self.half * jnp.clip(action, -1.0, 1.0)

    def observe(self, raw_obs: jax.Array) -> jax.Array:
        return features(raw_obs, self.angular)

    def reset(self, rng: jax.Array) -> State:
        sim_state = self.env.reset(rng)
        zero = jnp.zeros(())
        return State(
            pipeline_state=sim_state,
            obs=self._obs(sim_state),
            reward=zero,
            done=zero,
            metrics={},
            info={},
        )

    def step(self, state: State, action: jax.Array) -> State:
        u = self.control(action)
        sim_state = self.env.step(state.pipeline_state, u, self.env.params)
        q, qd = self.env.qqd(sim_state)
        return state.replace(
            pipeline_state=sim_state,
            obs=self._obs(sim_state),
            reward=self.env.task.reward(q, qd, u),
            done=jnp.zeros(()),
        )

    def _obs(self, sim_state) -> jax.Array:
        return self.observe(self.env.observe(sim_state, self.env.params))

    @property
    def observation_size(self) -> int:
        return int(self.observe(jnp.zeros(self.env.sim.n_obs)).shape[-1])

    @property
    def action_size(self) -> int:
        return self.env.sim.n_act

    @property
    def backend(self) -> str:
        return "hds"
