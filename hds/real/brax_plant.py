"""A plant made of the simulator itself plus hidden effects, applied exactly (sign law)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hds.envs import Env


class BraxPlant:
    def __init__(self, env: Env):
        self.env = env
        sim = env.sim
        self.obs_names, self.action_names, self.dt = sim.obs_names, sim.action_names, sim.dt
        self.ctrl_range = sim.ctrl_range
        self._init = jax.jit(jax.vmap(sim.init, in_axes=(0, 0, None)))
        self._step = jax.jit(jax.vmap(sim.step, in_axes=(None, 0, 0)))
        self._observe = jax.jit(jax.vmap(sim.observe, in_axes=(None, 0)))
        self._state = None

    def reset(self, q, qd):
        self._state = self._init(
            jnp.asarray(q, jnp.float32), jnp.asarray(qd, jnp.float32), self.env.params
        )
        return np.asarray(self._observe(self.env.params, self._state))

    def step(self, u):
        self._state = self._step(self.env.params, self._state, jnp.asarray(u, jnp.float32))
        return np.asarray(self._observe(self.env.params, self._state))

    def state(self):
        return np.asarray(self._state.q), np.asarray(self._state.qd)

    def noise_state(self) -> dict:
        """Its measurements are noise-free: nothing to restore."""
        return {}

    def set_noise_state(self, state: dict) -> None:
        if state:
            raise ValueError("a brax plant has no measurement noise to restore")
