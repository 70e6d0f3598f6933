"""Actuator effects: gain error, offset, dead zone, action delay and first-order lag."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from hds.effects.base import ACTUATOR, COMMAND, SUBSTEP, SYSTEM, Effect, Param


class ActuatorGain(Effect):
    name = "actuator_gain"
    target_kind = ACTUATOR
    description = "the actuator's force is this multiple of its nominal force (gear scaling)"
    physical_name = "actuator gain error"
    params = (Param("gain", "1 = nominal", 1.0, lower=0.0, fit_bounds=(0.05, 20.0)),)
    stage, order = SYSTEM, 1
    mjcf = "actuator gear"
    mujoco_field = ("actuator", "gear", 0, "scale")
    needs = "span"

    def modify_system(self, site, p, sys):
        gain = p["gain"]
        sys = sys.replace(
            actuator=sys.actuator.replace(gear=sys.actuator.gear.at[site.index].multiply(gain))
        )
        if hasattr(sys, "actuator_gear"):  # the mjx backend reads MuJoCo's own fields
            sys = sys.replace(actuator_gear=sys.actuator_gear.at[site.index, 0].multiply(gain))
        return sys

    def write_mjcf(self, spec, site, p):
        actuator = spec.actuator(site.target)
        actuator.gear = np.asarray(actuator.gear) * p["gain"]


class ActuatorOffset(Effect):
    name = "actuator_offset"
    target_kind = ACTUATOR
    description = "a constant added to the control before the actuator saturates"
    physical_name = "actuator offset (a constant added to the control)"
    params = (Param("offset", "control units", 0.0),)
    stage, order = COMMAND, 2
    mujoco_field = ("actuator", "biasprm", 0, "bias")

    def command(self, site, p, state, u, sharpness):
        return u.at[site.index].add(p["offset"]), state

    def plant_command(self, site, p, state, u):
        u[:, site.index] += p["offset"]
        return u, state


def soft_clip(u, half, sharpness):
    """clip(u, -half, half); a softplus-smoothed version when sharpness is given."""
    if sharpness is None:
        return jnp.clip(u, -half, half)
    sp = jax.nn.softplus
    return (sp(sharpness * (u + half)) - sp(sharpness * (u - half))) / sharpness - half


class ActuatorDeadzone(Effect):
    name = "actuator_deadzone"
    target_kind = ACTUATOR
    description = "controls within +-width/2 produce no force; outside, the band is subtracted"
    physical_name = "actuator dead zone"
    params = (Param("width", "control units", 0.0, lower=0.0),)
    stage, order = COMMAND, 1
    mujoco_field = "MuJoCo has no dead-zone field"
    needs = "span"

    def command(self, site, p, state, u, sharpness):
        half = 0.5 * p["width"]
        return u.at[site.index].set(
            u[site.index] - soft_clip(u[site.index], half, sharpness)
        ), state

    def plant_command(self, site, p, state, u):
        half = 0.5 * p["width"]
        u[:, site.index] -= np.clip(u[:, site.index], -half, half)
        return u, state


class ActionDelay(Effect):
    """Its length is static (it sets the buffer's shape): `site.static("steps")`."""

    name = "action_delay"
    target_kind = ACTUATOR
    description = "the actuator applies the control given this many environment steps earlier"
    physical_name = "action delay (dead time)"
    params = (Param("steps", "environment steps", 0, lower=0, upper=50, discrete=True),)
    stage, order = COMMAND, 0
    mujoco_field = (
        "a whole number of environment steps: MuJoCo's optimizer fits continuous fields "
        "(apply it to the recorded controls)"
    )
    needs = "changes"
    shifts_actions = True

    def init_state(self, site):
        return jnp.zeros((site.static("steps"),))

    def command(self, site, p, state, u, sharpness):
        if site.static("steps") == 0:
            return u, state
        applied = state[0]
        state = jnp.concatenate([state[1:], u[site.index][None]])
        return u.at[site.index].set(applied), state

    def plant_state(self, site, episodes):
        return np.zeros((episodes, site.static("steps")))

    def plant_command(self, site, p, state, u):
        if site.static("steps") == 0:
            return u, state
        applied = state[:, 0]
        state = np.concatenate([state[:, 1:], u[:, site.index, None]], axis=1)
        u[:, site.index] = applied
        return u, state


class ActuatorLag(Effect):
    name = "actuator_lag"
    target_kind = ACTUATOR
    description = (
        "first-order actuator dynamics: the applied control follows the command "
        "with this time constant"
    )
    physical_name = "first-order actuator lag"
    params = (Param("time_constant", "s", 0.0, lower=0.0, fit_start_in_timesteps=0.5),)
    stage, order = SUBSTEP, 0
    mjcf = "actuator dyntype filterexact"
    mujoco_field = ("actuator", "dynprm", 0, "add")
    needs = "changes"

    def init_state(self, site):
        return jnp.zeros(())

    def substep(self, site, p, state, u, force, q, qd, h, sharpness, gradient_sharpness):
        tau = jnp.maximum(p["time_constant"], 1e-6)
        y = state + (1.0 - jnp.exp(-h / tau)) * (u[site.index] - state)
        # The force uses the updated output (MuJoCo's actearly), so a time constant of 0
        # passes the control through unchanged: the effect's nominal value is a no-op.
        return u.at[site.index].set(y), force, y

    def write_mjcf(self, spec, site, p):
        actuator = spec.actuator(site.target)
        if actuator.dyntype != mujoco.mjtDyn.mjDYN_NONE:
            raise ValueError(
                f"actuator_lag@{site.target}: the actuator already has "
                f"dynamics ({actuator.dyntype.name}); remove them or the effect"
            )
        actuator.dyntype = mujoco.mjtDyn.mjDYN_FILTEREXACT
        actuator.dynprm[0] = p["time_constant"]
        actuator.actearly = 1  # the force uses the updated filter state, as the simulator
