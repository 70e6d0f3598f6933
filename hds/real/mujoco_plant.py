"""A plant made of C MuJoCo on the simulator's own MJCF, plus hidden effects.

The effects MuJoCo has natively are written into the model (`mujoco_spec`, whose
`spec.to_xml()` is an MJCF of the "real" system):
  coulomb_friction  joint frictionloss (added)     viscous_damping  joint damping (added)
  actuator_gain     actuator gear (scaled)         mass_scale       body mass, inertia (scaled)
  actuator_lag      actuator dyntype filterexact, dynprm[0] = time constant, actearly
The others act in `MujocoPlant.step`, with the semantics of `hds.effects.apply.EffectSet`:
action_delay, actuator_deadzone and actuator_offset on the control (then clipped to ctrlrange),
sensor_bias on the returned observation. Everything is float64.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from hds.effects import place
from hds.envs.system import load_spec, state_names, target_names


def place_effects(spec: mujoco.MjSpec, effects, friction_gap: float = 1.0):
    """Check `effects` against the spec's model (`hds.effects.place`), write the MuJoCo-native
    ones into `spec` (in place) and return the placed (EffectSet, params) of all of them."""
    placed, params = place(effects, target_names(spec.compile()), friction_gap)
    for site, p in zip(placed.sites, params, strict=True):
        value = {k: float(v) for k, v in p.items()}
        if site.name == "coulomb_friction":
            spec.joint(site.target).frictionloss += value["force"]
        elif site.name == "viscous_damping":
            spec.joint(site.target).damping[0] += value["coefficient"]
        elif site.name == "actuator_gain":
            actuator = spec.actuator(site.target)
            actuator.gear = np.asarray(actuator.gear) * value["gain"]
        elif site.name == "actuator_lag":
            actuator = spec.actuator(site.target)
            if actuator.dyntype != mujoco.mjtDyn.mjDYN_NONE:
                raise ValueError(
                    f"actuator_lag@{site.target}: the actuator already has "
                    f"dynamics ({actuator.dyntype.name}); remove them or the effect"
                )
            actuator.dyntype = mujoco.mjtDyn.mjDYN_FILTEREXACT
            actuator.dynprm[0] = value["time_constant"]
            actuator.actearly = 1  # the force uses the updated filter state, as the simulator
        elif site.name == "mass_scale":
            _scale_mass(spec, spec.body(site.target), value["scale"])
    return placed, params


def _scale_mass(spec: mujoco.MjSpec, body, scale: float) -> None:
    """Scale a body's mass and inertia: through its geoms when the compiler infers them."""
    mode = spec.compiler.inertiafromgeom
    from_geoms = mode == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE or (
        mode == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_AUTO and not body.explicitinertial
    )
    if from_geoms:  # mass and inertia are linear in density (or in a geom's given mass)
        for geom in body.geoms:
            geom.density *= scale
            if not math.isnan(geom.mass):
                geom.mass *= scale
    else:
        body.mass *= scale
        body.inertia = np.asarray(body.inertia) * scale
        body.fullinertia = np.asarray(body.fullinertia) * scale  # NaN (unused) stays NaN


def mujoco_spec(env_cfg, effects=(), friction_gap: float = 1.0) -> mujoco.MjSpec:
    """The MjSpec of an `env` config's system with the MuJoCo-native effects applied."""
    spec = load_spec(env_cfg.xml, env_cfg.timestep)
    place_effects(spec, effects, friction_gap)
    return spec


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
        self._data: list[mujoco.MjData] = []
        self._delay: dict[int, np.ndarray] = {}

    def reset(self, q, qd) -> np.ndarray:
        q, qd = np.asarray(q, np.float64), np.asarray(qd, np.float64)
        if len(self._data) != len(q):
            self._data = [mujoco.MjData(self.model) for _ in range(len(q))]
        for data, qi, qdi in zip(self._data, q, qd, strict=True):
            mujoco.mj_resetData(self.model, data)  # also zeroes activations (lag filters)
            data.qpos[:], data.qvel[:] = qi, qdi
            mujoco.mj_forward(self.model, data)
        self._delay = {i: np.zeros((len(q), s.steps)) for i, s in self.effects.of("action_delay")}
        return self._observe()

    def step(self, u) -> np.ndarray:
        u = np.array(u, dtype=np.float64)  # a copy: the effects below edit it
        if u.shape != (len(self._data), self.model.nu):
            raise ValueError(
                f"step expects u of shape [B, {self.model.nu}] with B from reset "
                f"({len(self._data)} episodes; call reset first), got {u.shape}"
            )
        for i, s in self.effects.of("action_delay"):
            if s.steps > 0:
                buf = self._delay[i]
                self._delay[i] = np.concatenate([buf[:, 1:], u[:, s.index, None]], axis=1)
                u[:, s.index] = buf[:, 0]
        for i, s in self.effects.of("actuator_deadzone"):
            half = 0.5 * self.params[i]["width"]
            u[:, s.index] -= np.clip(u[:, s.index], -half, half)
        for i, s in self.effects.of("actuator_offset"):
            u[:, s.index] += self.params[i]["offset"]
        u = np.clip(u, self.ctrl_range[:, 0], self.ctrl_range[:, 1])
        for data, ui in zip(self._data, u, strict=True):
            data.ctrl[:] = ui
            mujoco.mj_step(self.model, data, nstep=self.frames)
        return self._observe()

    def state(self) -> tuple[np.ndarray, np.ndarray]:
        return (
            np.stack([d.qpos.copy() for d in self._data]),
            np.stack([d.qvel.copy() for d in self._data]),
        )

    def _observe(self) -> np.ndarray:
        obs = np.concatenate(self.state(), axis=1)
        for i, s in self.effects.of("sensor_bias"):
            obs[:, s.index] += self.params[i]["bias"]
        return obs
