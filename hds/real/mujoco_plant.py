"""A plant made of C MuJoCo on the simulator's own MJCF, plus hidden effects.

Each effect brings its exact law (hds.effects.base.Effect): the ones MuJoCo has natively
(`Effect.mjcf`: frictionloss, damping, gear, filterexact dynamics, mass) are written into
the model (`mujoco_spec`, whose `spec.to_xml()` is an MJCF of the "real" system); the others
act in `MujocoPlant.step` in numpy, in the order of the simulator's stages: on the control
(then clipped to ctrlrange), as a joint force held over the step (qfrc_applied), or on the
returned observation. Stepwise laws (`Effect.plant_stepwise`: friction that varies with speed,
cogging, backlash) set the control, the joint forces and MuJoCo's frictionloss from the state
at every physics step, the plant then stepping one physics step at a time. Everything is
float64.
"""

from __future__ import annotations

import mujoco
import numpy as np

from hds.effects import place
from hds.effects.base import COMMAND, OBSERVE, SUBSTEP, SYSTEM, PlantLoads
from hds.effects.library import effect_type
from hds.envs.system import load_spec, state_names, target_names


def place_effects(spec: mujoco.MjSpec, effects, friction_gap: float = 1.0):
    """Check `effects` against the spec's model (`hds.effects.place`), write the MuJoCo-native
    ones into `spec` (in place) and return the placed (EffectSet, params) of all of them."""
    placed, params = place(effects, target_names(spec.compile()), friction_gap)
    for site, p in zip(placed.sites, params, strict=True):
        effect = effect_type(site.name)
        if effect.mjcf or effect.stage == SYSTEM:  # a system edit has only this law here
            effect.write_mjcf(spec, site, {k: float(v) for k, v in p.items()})
    return placed, params


def mujoco_spec(env_cfg, effects=(), friction_gap: float = 1.0) -> mujoco.MjSpec:
    """The MjSpec of an `env` config's system with the MuJoCo-native effects applied."""
    spec = load_spec(env_cfg.xml, env_cfg.timestep)
    place_effects(spec, effects, friction_gap)
    return spec


def mjcf_text(env_cfg, effects=(), friction_gap: float = 1.0, source: str = "hds") -> str:
    """The MJCF of `mujoco_spec`, headed by a comment naming which effects it carries as
    MuJoCo's own elements and which MJCF cannot express (with their values: hds's simulators
    apply them, and hds.real.MujocoPlant those with a plant law)."""
    from hds.effects.apply import applied

    effects = applied(effects, friction_gap)
    xml = mujoco_spec(env_cfg, effects).to_xml()
    mjcf = {e["name"]: effect_type(e["name"]).mjcf for e in effects}
    native = [f"{e['name']}@{e['target']} ({mjcf[e['name']]})" for e in effects if mjcf[e["name"]]]
    other = [f"{e['name']}@{e['target']} {e['params']}" for e in effects if not mjcf[e["name"]]]
    comment = (
        f"<!-- {source}. MuJoCo-native here: {', '.join(native) or 'none'}. Not expressible in "
        "MJCF (hds's simulators apply them; hds.real.MujocoPlant those with a plant law, in its "
        f"controller, force or sensor path): {', '.join(other) or 'none'}. -->\n"
    )
    return comment + xml


class MujocoPlant:
    """C MuJoCo on B episodes (one MjData each); see `hds.real` for the interface."""

    def __init__(self, env_cfg, effects=(), friction_gap: float = 1.0):
        spec = load_spec(env_cfg.xml, env_cfg.timestep)
        self.effects, params = place_effects(spec, list(effects), friction_gap)
        self.params = [{k: float(v) for k, v in p.items()} for p in params]
        self.model = spec.compile()
        self.frames = int(env_cfg.frames_per_step)
        self.dt = float(self.model.opt.timestep) * self.frames
        self.obs_names = tuple(state_names(self.model))
        self.action_names = tuple(self.model.actuator(a).name for a in range(self.model.nu))
        self.ctrl_range = np.array(self.model.actuator_ctrlrange, dtype=np.float64)
        self.ctrl_range[self.model.actuator_ctrllimited == 0] = [-np.inf, np.inf]
        self._forces = np.zeros(self.model.nv)  # the substep effects MuJoCo lacks
        self._stepwise = [row for row in self.effects.at(SUBSTEP) if row[2].plant_stepwise]
        for i, site, effect in self.effects.at(SUBSTEP):
            if not effect.mjcf and not effect.plant_stepwise:
                self._forces[site.index] += effect.plant_force(site, self.params[i])
        self._frictionloss = np.array(self.model.dof_frictionloss)  # the stepwise laws add to it
        self._data: list[mujoco.MjData] = []
        self._states: dict[int, np.ndarray] = {}
        # observation states (noise generators) last as long as the plant: a real sensor's
        # noise does not repeat at every reset
        self._observe_states = {
            i: effect.plant_state(site, 0) for i, site, effect in self.effects.at(OBSERVE)
        }

    def reset(self, q, qd) -> np.ndarray:
        q, qd = np.asarray(q, np.float64), np.asarray(qd, np.float64)
        if len(self._data) != len(q):
            self._data = [mujoco.MjData(self.model) for _ in range(len(q))]
        for data, qi, qdi in zip(self._data, q, qd, strict=True):
            mujoco.mj_resetData(self.model, data)  # also zeroes activations (lag filters)
            data.qpos[:], data.qvel[:] = qi, qdi
            if self._forces.any():
                data.qfrc_applied[:] = self._forces
            mujoco.mj_forward(self.model, data)
        self._states = {
            i: effect.plant_state(site, len(q))
            for i, site, effect in [*self.effects.at(COMMAND), *self._stepwise]
        }
        return self._observe()

    def step(self, u) -> np.ndarray:
        u = np.array(u, dtype=np.float64)  # a copy: the effects below edit it
        if u.shape != (len(self._data), self.model.nu):
            raise ValueError(
                f"step expects u of shape [B, {self.model.nu}] with B from reset "
                f"({len(self._data)} episodes; call reset first), got {u.shape}"
            )
        for i, site, effect in self.effects.at(COMMAND):
            u, self._states[i] = effect.plant_command(site, self.params[i], self._states[i], u)
        u = np.clip(u, self.ctrl_range[:, 0], self.ctrl_range[:, 1])
        if self._stepwise:
            for _ in range(self.frames):
                self._physics_step(u)
            return self._observe()
        for data, ui in zip(self._data, u, strict=True):
            data.ctrl[:] = ui
            mujoco.mj_step(self.model, data, nstep=self.frames)
        return self._observe()

    def _physics_step(self, u) -> None:
        """One physics step of every episode with the stepwise laws' loads, computed from the
        state at its start (as the simulator's substep computes its forces)."""
        q, qd = self.state()
        batch = len(self._data)
        loads = PlantLoads(
            u.copy(), np.tile(self._forces, (batch, 1)), np.tile(self._frictionloss, (batch, 1))
        )
        for i, site, effect in self._stepwise:
            self._states[i] = effect.plant_substep(
                site, self.params[i], self._states[i], loads, q, qd, self.model.opt.timestep
            )
        try:
            for b, data in enumerate(self._data):
                data.ctrl[:] = loads.ctrl[b]
                data.qfrc_applied[:] = loads.force[b]
                self.model.dof_frictionloss[:] = loads.frictionloss[b]  # this episode's
                mujoco.mj_step(self.model, data)
        finally:
            self.model.dof_frictionloss[:] = self._frictionloss

    def noise_state(self) -> dict:
        """Where the measurement noise's generators stand (JSON-ready): a run that resumes
        past this plant's use restores it (`set_noise_state`), to draw the noise an
        uninterrupted run draws next."""
        return {
            str(i): state.bit_generator.state
            for i, state in self._observe_states.items()
            if isinstance(state, np.random.Generator)
        }

    def set_noise_state(self, state: dict) -> None:
        for i, generator_state in state.items():
            self._observe_states[int(i)].bit_generator.state = generator_state

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        return (
            np.stack([d.qpos.copy() for d in self._data]),
            np.stack([d.qvel.copy() for d in self._data]),
        )

    def _observe(self) -> np.ndarray:
        obs = np.concatenate(self.state(), axis=1)
        for i, site, effect in self.effects.at(OBSERVE):
            state = self._observe_states[i]
            if state is None:
                obs = effect.plant_observe(site, self.params[i], obs)
            else:
                obs = effect.plant_observe(site, self.params[i], obs, state)
        return obs
