"""Effects of a lab's robot that discovery's library does not search: friction with a static
(Stribeck) peak, friction that varies along the travel (a rough patch), a motor's cogging
torque, backlash in a belt drive, the amplifier's saturation, sensor noise and encoder
quantisation.

The lab plants (`hds.real.lab`, `real=lab_cartpole`, `real=lab_furuta`) hide them. Each has
its exact law on the C MuJoCo plant (MuJoCo's own frictionloss set at every physics step, a
force or a control computed from the state at every physics step: `Effect.plant_stepwise`,
or numpy on the control and the measurement) and a differentiable replica in jax, which the
oracle trains on (`simulator=real` builds the simulator with the plant's effects). None is
one of discovery's candidates (`candidate = False`): they stand for what a library lacks, and
the lab study measures what discovery makes of them.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from hds.effects.actuator import soft_clip
from hds.effects.base import (
    ACTUATOR,
    COMMAND,
    JOINT,
    OBSERVATION,
    OBSERVE,
    SUBSTEP,
    Effect,
    Param,
)
from hds.effects.friction import friction_direction, stick_sharpness


def _check_position_index(target: str, names: dict, where: str) -> None:
    """A law that reads a joint's position reads it at the joint's dof index."""
    if names["observation"].get(f"q_{target}") != names["joint"][target]:
        raise ValueError(
            f"{where}: the joint's position and velocity have different indices (a free "
            "or ball joint comes first); put the one-dof joints first in the MJCF"
        )


def stribeck_magnitude(xp, p, qd):
    """Dry friction's magnitude at speed qd: the sliding (Coulomb) level plus the static
    excess, which decays with speed over the Stribeck velocity (a Gaussian decay, the common
    form: Olsson et al. 1998)."""
    excess = p["static"] - p["force"]
    return p["force"] + excess * xp.exp(-((qd / p["velocity"]) ** 2))


class StribeckFriction(Effect):
    name = "stribeck_friction"
    target_kind = JOINT
    description = (
        "dry friction whose magnitude is the static (breakaway) level at rest and decays to "
        "the sliding (Coulomb) level over the Stribeck velocity: F(v) = Fc + (Fs - Fc) "
        "exp(-(v/vs)^2) against the motion (smoothed as F(v) tanh(k v) in the simulator, k no "
        "sharper than a substep carries at the static level; in the C MuJoCo plant MuJoCo's "
        "frictionloss set to F(v) at every physics step, which holds a joint at rest up to Fs)"
    )
    physical_name = "Stribeck friction (static peak above Coulomb)"
    params = (
        Param("force", "N or N m", 0.0, lower=0.0),
        Param("static", "N or N m", 0.0, lower=0.0),
        Param("velocity", "m/s or rad/s", 1.0, lower=1e-6),
    )
    stage, order = SUBSTEP, 1
    candidate = False
    plant_stepwise = True

    def check_site(self, target, values, names, where):
        if values["static"] < values["force"]:
            raise ValueError(
                f"{where}: static = {values['static']} is below force = {values['force']}; "
                "the breakaway friction is at least the sliding one"
            )

    def substep(self, site, p, state, u, force, q, qd, h, sharpness, gradient_sharpness):
        v = qd[site.index]
        if sharpness is not None and site.mobility > 0:
            # the stiffest the law gets is at rest, at the static level
            sharpness = jnp.minimum(sharpness, stick_sharpness(p["static"], site.mobility, h))
        direction = friction_direction(v, sharpness, gradient_sharpness)
        return u, force.at[site.index].add(-stribeck_magnitude(jnp, p, v) * direction), state

    def plant_substep(self, site, p, state, loads, q, qd, h):
        loads.frictionloss[:, site.index] += stribeck_magnitude(np, p, qd[:, site.index])
        return state


def patch_magnitude(xp, p, q):
    """Dry friction's extra magnitude at position q of a rough patch: the peak `force` at
    `center`, falling off as a Gaussian of half-width `width` (a worn or dirty stretch of a
    rail, a tight spot of a bearing)."""
    return p["force"] * xp.exp(-(((q - p["center"]) / p["width"]) ** 2))


class PatchFriction(Effect):
    name = "patch_friction"
    target_kind = JOINT
    description = (
        "dry friction that varies along the joint's travel, a rough patch: F(q) = force x "
        "exp(-((q - center) / width)^2) against the motion, on top of the joint's own friction "
        "(smoothed as F(q) tanh(k v) in the simulator, k no sharper than a substep carries "
        "at the peak; in the C MuJoCo plant added to MuJoCo's frictionloss at every physics "
        "step, which holds a joint at rest in the patch up to F(q))"
    )
    physical_name = "friction that varies along the travel (a rough patch)"
    params = (
        Param("force", "N or N m", 0.0, lower=0.0),
        Param("center", "m or rad", 0.0),
        Param("width", "m or rad", 1.0, lower=1e-6),
    )
    stage, order = SUBSTEP, 1
    candidate = False
    plant_stepwise = True

    def check_site(self, target, values, names, where):
        _check_position_index(target, names, where)

    def substep(self, site, p, state, u, force, q, qd, h, sharpness, gradient_sharpness):
        j = site.index
        if sharpness is not None and site.mobility > 0:
            # the cap at the peak: beside another dry friction on the joint the two caps add,
            # and a joint at rest in the patch chatters at under h w F / 2 (mm/s on the cart)
            sharpness = jnp.minimum(sharpness, stick_sharpness(p["force"], site.mobility, h))
        direction = friction_direction(qd[j], sharpness, gradient_sharpness)
        return u, force.at[j].add(-patch_magnitude(jnp, p, q[j]) * direction), state

    def plant_substep(self, site, p, state, loads, q, qd, h):
        j = site.index
        loads.frictionloss[:, j] += patch_magnitude(np, p, q[:, j])
        return state


def cogging_torque(xp, p, periods, q):
    return p["amplitude"] * xp.sin(periods * q + p["phase"])


class CoggingTorque(Effect):
    name = "cogging_torque"
    target_kind = JOINT
    description = (
        "a motor's cogging: a torque periodic in the shaft's angle, amplitude x sin(periods x "
        "q + phase), `periods` whole periods a turn (the rotor's magnets passing the stator's "
        "teeth); the same law in the simulator and the plant (computed at every physics step)"
    )
    physical_name = "cogging torque"
    params = (
        Param("amplitude", "N m", 0.0),
        Param("periods", "periods a turn", 1, lower=1, upper=1000, discrete=True),
        Param("phase", "rad", 0.0),
    )
    stage, order = SUBSTEP, 2
    candidate = False
    plant_stepwise = True

    def check_site(self, target, values, names, where):
        _check_position_index(target, names, where)

    def substep(self, site, p, state, u, force, q, qd, h, sharpness, gradient_sharpness):
        j = site.index
        tau = cogging_torque(jnp, p, site.static("periods"), q[j])
        return u, force.at[j].add(tau), state

    def plant_substep(self, site, p, state, loads, q, qd, h):
        j = site.index
        loads.force[:, j] += cogging_torque(np, p, site.static("periods"), q[:, j])
        return state


def backlash_law(xp, p, delta, sigma, u, h):
    """One physics step of h seconds of the drive side of a transmission with play: delta, its
    position in the gap relative to the load (0: centred, +-gap/2: touching), sigma, its
    velocity relative to the load. Pressed against the side it pushes towards, the drive
    transmits the control u; otherwise the load gets none of it and the drive crosses the gap
    at acceleration u / inertia (the load's own acceleration neglected: the drive's inertia
    is the small one), stopping where it touches a side (inelastically). Returns (the control
    transmitted, the next delta, the next sigma)."""
    half = 0.5 * p["gap"]
    engaged = ((delta >= half) & (u > 0)) | ((delta <= -half) & (u < 0))
    sigma_free = sigma + h * u / p["inertia"]
    delta_free = delta + h * sigma_free
    touches = xp.abs(delta_free) >= half
    delta_next = xp.where(engaged, delta, xp.clip(delta_free, -half, half))
    sigma_next = xp.where(engaged | touches, 0.0 * sigma, sigma_free)
    return xp.where(engaged, u, 0.0 * u), delta_next, sigma_next


class Backlash(Effect):
    name = "backlash"
    target_kind = ACTUATOR
    description = (
        "play in the actuator's transmission (a belt drive's backlash): after the control "
        "changes sign the drive side crosses a gap of `gap` (m or rad of the joint) at "
        "acceleration u / inertia before it pushes again, and the joint gets none of the "
        "control meanwhile; the same discrete law in the simulator (piecewise differentiable: "
        "through the control while engaged and through the drive's motion in the gap) and the "
        "plant, at every physics step"
    )
    physical_name = "backlash (transmission play)"
    params = (
        Param("gap", "m or rad", 0.0, lower=0.0),
        # the drive side's inertia over the actuator's gear: control units per m/s^2 (rad/s^2)
        Param("inertia", "control units s^2/m (or /rad)", 1.0, lower=1e-9),
    )
    stage, order = SUBSTEP, 1  # after the lag: it acts on the force the actuator makes
    candidate = False
    plant_stepwise = True

    def init_state(self, site):
        return jnp.zeros(2)

    def substep(self, site, p, state, u, force, q, qd, h, sharpness, gradient_sharpness):
        a = site.index
        sent, delta, sigma = backlash_law(jnp, p, state[0], state[1], u[a], h)
        return u.at[a].set(sent), force, jnp.stack([delta, sigma])

    def plant_state(self, site, episodes):
        return np.zeros((episodes, 2))

    def plant_substep(self, site, p, state, loads, q, qd, h):
        a = site.index
        sent, delta, sigma = backlash_law(np, p, state[:, 0], state[:, 1], loads.ctrl[:, a], h)
        loads.ctrl[:, a] = sent
        return np.stack([delta, sigma], axis=1)


class ActuatorSaturation(Effect):
    name = "actuator_saturation"
    target_kind = ACTUATOR
    description = (
        "the amplifier saturates at +-limit (control units), inside the actuator's control "
        "range (smoothed with softplus in the simulator as the dead zone is, exact in plants)"
    )
    physical_name = "actuator saturation"
    params = (Param("limit", "control units", math.inf, lower=0.0),)
    stage, order = COMMAND, 3  # after the offset: the amplifier's output stage
    candidate = False

    def command(self, site, p, state, u, sharpness):
        limit = p["limit"]
        finite = jnp.isfinite(limit)  # the nominal (infinite) limit: the control as it is
        clipped = soft_clip(u[site.index], jnp.where(finite, limit, 1.0), sharpness)
        return u.at[site.index].set(jnp.where(finite, clipped, u[site.index])), state

    def plant_command(self, site, p, state, u):
        u[:, site.index] = np.clip(u[:, site.index], -p["limit"], p["limit"])
        return u, state


class SensorNoise(Effect):
    name = "sensor_noise"
    target_kind = OBSERVATION
    description = (
        "white Gaussian noise of standard deviation `std` on one measured observation, drawn "
        "from a generator seeded by `seed` that lives as long as the plant; the simulator's "
        "replica is noise-free (the noise's mean)"
    )
    physical_name = "sensor noise"
    params = (
        Param("std", "observation units", 0.0, lower=0.0),
        Param("seed", "integer", 0, lower=0, upper=2**31 - 1, discrete=True),
    )
    stage, order = OBSERVE, 0
    candidate = False

    def observe(self, site, p, obs):
        return obs

    def plant_state(self, site, episodes):
        return np.random.default_rng([site.static("seed"), site.index])

    def plant_observe(self, site, p, obs, rng=None):
        obs[:, site.index] += p["std"] * rng.standard_normal(len(obs))
        return obs


class EncoderQuantization(Effect):
    name = "encoder_quantization"
    target_kind = OBSERVATION
    description = (
        "the measurement is rounded to whole steps of `step` (an encoder: 2 pi / 2048 rad for "
        "2,048 counts a turn); in the simulator rounded too, with the identity's gradient "
        "(straight through)"
    )
    physical_name = "encoder quantisation"
    params = (Param("step", "observation units", 0.0, lower=0.0),)
    stage, order = OBSERVE, 1  # after the noise: the encoder's count is what is read

    candidate = False

    def observe(self, site, p, obs):
        x, step = obs[site.index], jnp.maximum(p["step"], 1e-12)
        rounded = jnp.where(p["step"] > 0, step * jnp.round(x / step), x)
        return obs.at[site.index].set(x + jax.lax.stop_gradient(rounded - x))

    def plant_observe(self, site, p, obs):
        if p["step"] > 0:
            obs[:, site.index] = p["step"] * np.round(obs[:, site.index] / p["step"])
        return obs


LAB_EFFECTS = (
    StribeckFriction,
    PatchFriction,
    CoggingTorque,
    Backlash,
    ActuatorSaturation,
    SensorNoise,
    EncoderQuantization,
)
