"""The simulated systems: an MJCF on a Brax backend (`system`) and its tasks (`tasks`)."""

from __future__ import annotations

from dataclasses import dataclass

import jax

from hds.effects import EffectParams
from hds.envs.system import SimState, Simulator, make_simulator
from hds.envs.tasks import Task, make_task


@dataclass(frozen=True, eq=False)
class Env:
    """A simulator, the parameters of the effects it models, and a task.

    It is an engine for the trainer: reset, step, observe and qqd are pure functions, and the
    effect parameters are an argument so they can be differentiated or vmapped."""

    sim: Simulator
    params: EffectParams
    task: Task

    def reset(self, key: jax.Array) -> SimState:
        return self.sim.init(*self.task.initial(key), self.params)

    def step(self, state: SimState, u: jax.Array, params: EffectParams) -> SimState:
        return self.sim.step(params, state, u)

    def observe(self, state: SimState, params: EffectParams) -> jax.Array:
        return self.sim.observe(params, state)

    @staticmethod
    def qqd(state: SimState):
        """The true state, which rewards are computed from."""
        return state.q, state.qd


def make_env(cfg, effects=None, sharpness="config", friction_gap: float = 1.0) -> Env:
    """Build the env of an `env` config; `effects` replaces the config's own list when given
    (plants add their hidden effects this way), `sharpness=None` makes effects exact."""
    sim, params = make_simulator(
        cfg.xml,
        backend=cfg.backend,
        timestep=cfg.timestep,
        frames=cfg.frames_per_step,
        effects=list(cfg.effects if effects is None else effects),
        sharpness=cfg.sharpness if sharpness == "config" else sharpness,
        friction_gap=friction_gap,
        gradient_sharpness=None if sharpness is None else cfg.gradient_sharpness,
    )
    task = make_task(cfg.task, sim.angular, sim.nq, sim.n_obs - sim.nq, sim.link_angles)
    return Env(sim, params, task)


__all__ = ["Env", "SimState", "Simulator", "Task", "make_env", "make_simulator"]
