"""A plant made of C MuJoCo on the simulator's own MJCF, plus hidden effects.

Each effect brings its exact law (hds.effects.base.Effect): the ones MuJoCo has natively
(`Effect.mjcf`: frictionloss, damping, gear, filterexact dynamics, mass) are written into
the model (`mujoco_spec`, whose `spec.to_xml()` is an MJCF of the "real" system); the others
act in `MujocoPlant.step` in numpy, in the order of the simulator's stages: on the control
(then clipped to ctrlrange), as a joint force held over the step (qfrc_applied), or on the
returned observation. Everything is float64.
"""

from __future__ import annotations

import mujoco
import numpy as np

from hds.effects import place
from hds.effects.base import COMMAND, OBSERVE, SUBSTEP, SYSTEM, Effect
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
        self._velocity_forces = []  # ... and those of them whose force follows the velocity
        for i, site, effect in self.effects.at(SUBSTEP):
            if effect.mjcf:
                continue
            if _overrides(effect, "plant_velocity_force"):
                self._velocity_forces.append((site, effect, self.params[i]))
            else:
                self._forces[site.index] += effect.plant_force(site, self.params[i])
        self._data: list[mujoco.MjData] = []
        self._states: dict[int, np.ndarray] = {}

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
            i: effect.plant_state(site, len(q)) for i, site, effect in self.effects.at(COMMAND)
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
        for data, ui in zip(self._data, u, strict=True):
            data.ctrl[:] = ui
            if not self._velocity_forces:
                mujoco.mj_step(self.model, data, nstep=self.frames)
                continue
            for _ in range(self.frames):  # a velocity's force, from each step's start
                data.qfrc_applied[:] = self._forces
                for site, effect, p in self._velocity_forces:
                    qd = float(data.qvel[site.index])
                    data.qfrc_applied[site.index] += effect.plant_velocity_force(site, p, qd)
                mujoco.mj_step(self.model, data)
        return self._observe()

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        return (
            np.stack([d.qpos.copy() for d in self._data]),
            np.stack([d.qvel.copy() for d in self._data]),
        )

    def _observe(self) -> np.ndarray:
        obs = np.concatenate(self.state(), axis=1)
        for i, site, effect in self.effects.at(OBSERVE):
            obs = effect.plant_observe(site, self.params[i], obs)
        return obs


def _overrides(effect, method: str) -> bool:
    """Whether the effect's class defines `method` (beyond the base class's refusal)."""
    return getattr(type(effect), method) is not getattr(Effect, method)
