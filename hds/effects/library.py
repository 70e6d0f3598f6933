"""The named physical effects: what each one is, where it acts, its parameters and units.

This module is pure metadata (no JAX): configs validate against it before anything compiles,
and the simulator (`hds.effects.apply`), the MuJoCo plant and gap discovery read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

JOINT, ACTUATOR, BODY, OBSERVATION = "joint", "actuator", "body", "observation"


@dataclass(frozen=True)
class Param:
    name: str
    unit: str
    nominal: float  # the value at which the effect does nothing
    lower: float = -math.inf
    upper: float = math.inf
    discrete: bool = False  # integer, fitted by enumeration rather than by gradient


@dataclass(frozen=True)
class EffectType:
    name: str
    target_kind: str
    description: str
    params: tuple[Param, ...]

    def param(self, name: str) -> Param:
        return next(p for p in self.params if p.name == name)


LIBRARY: dict[str, EffectType] = {
    e.name: e
    for e in (
        EffectType(
            "coulomb_friction",
            JOINT,
            "dry friction opposing the joint's velocity with constant magnitude "
            "(smoothed as F tanh(k qd) in the differentiable simulator, exact sign law in plants)",
            (Param("force", "N or N m", 0.0, lower=0.0),),
        ),
        EffectType(
            "viscous_damping",
            JOINT,
            "friction proportional to the joint's velocity",
            (Param("coefficient", "N s/m or N m s/rad", 0.0, lower=0.0),),
        ),
        EffectType(
            "actuator_gain",
            ACTUATOR,
            "the actuator's force is this multiple of its nominal force (gear scaling)",
            (Param("gain", "1 = nominal", 1.0, lower=0.0),),
        ),
        EffectType(
            "actuator_offset",
            ACTUATOR,
            "a constant added to the control before the actuator saturates",
            (Param("offset", "control units", 0.0),),
        ),
        EffectType(
            "actuator_deadzone",
            ACTUATOR,
            "controls within +-width/2 produce no force; outside, the band is subtracted",
            (Param("width", "control units", 0.0, lower=0.0),),
        ),
        EffectType(
            "action_delay",
            ACTUATOR,
            "the actuator applies the control given this many environment steps earlier",
            (Param("steps", "environment steps", 0, lower=0, upper=50, discrete=True),),
        ),
        EffectType(
            "actuator_lag",
            ACTUATOR,
            "first-order actuator dynamics: the applied control follows the command "
            "with this time constant",
            (Param("time_constant", "s", 0.0, lower=0.0),),
        ),
        EffectType(
            "mass_scale",
            BODY,
            "the body's mass, and with it its inertia, is this multiple of the nominal",
            (Param("scale", "1 = nominal", 1.0, lower=0.0),),
        ),
        EffectType(
            "sensor_bias",
            OBSERVATION,
            "a constant added to one measured observation",
            (Param("bias", "observation units", 0.0),),
        ),
    )
}

# Effects whose magnitude `real.friction_gap` scales.
FRICTION_EFFECTS = {"coulomb_friction": "force", "viscous_damping": "coefficient"}


def effect_type(name: str) -> EffectType:
    if name not in LIBRARY:
        raise ValueError(f"unknown effect '{name}'; the library has: {', '.join(LIBRARY)}")
    return LIBRARY[name]


def check_params(name: str, params: dict[str, float], where: str = "effect") -> dict[str, float]:
    """Fill defaults and check names and ranges; return the complete parameter dict."""
    etype = effect_type(name)
    allowed = [p.name for p in etype.params]
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        raise ValueError(
            f"{where}: effect '{name}' has no parameter {unknown}; its parameters are {allowed}"
        )
    out = {}
    for p in etype.params:
        value = params.get(p.name, p.nominal)
        if not isinstance(value, (int, float)) or isinstance(value, bool) or math.isnan(value):
            raise ValueError(f"{where}: {name}.{p.name} must be a number, got {value!r}")
        if p.discrete and value != int(value):
            raise ValueError(f"{where}: {name}.{p.name} must be an integer, got {value}")
        if not p.lower <= value <= p.upper:
            raise ValueError(
                f"{where}: {name}.{p.name} = {value} is out of range [{p.lower}, {p.upper}] "
                f"({p.unit})"
            )
        out[p.name] = int(value) if p.discrete else float(value)
    return out
