"""Sensor effects: a constant bias of one measured observation."""

from __future__ import annotations

from hds.effects.base import OBSERVATION, OBSERVE, Effect, Param


class SensorBias(Effect):
    name = "sensor_bias"
    target_kind = OBSERVATION
    description = "a constant added to one measured observation"
    physical_name = "sensor bias"
    params = (Param("bias", "observation units", 0.0),)
    stage = OBSERVE
    mujoco_field = (
        "acts on the measurement, not the model (mujoco.sysid.apply_bias in a modify_residual)"
    )

    def observe(self, site, p, obs):
        return obs.at[site.index].add(p["bias"])

    def plant_observe(self, site, p, obs):
        obs[:, site.index] += p["bias"]
        return obs
