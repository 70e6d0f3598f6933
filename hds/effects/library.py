"""The library of named physical effects: one registry, `LIBRARY`, in registration order.

Each effect is one object (`hds.effects.base.Effect`) in the file of its family; configs
validate against the registry before anything compiles, and the simulator
(`hds.effects.apply`), the MuJoCo plant and gap discovery ask it for everything about an
effect. Adding one: a subclass of `Effect` in a file, and `register(MyEffect())`.
"""

from __future__ import annotations

import math

from hds.effects.actuator import (
    ActionDelay,
    ActuatorDeadzone,
    ActuatorGain,
    ActuatorLag,
    ActuatorOffset,
)
from hds.effects.base import STAGES, TARGET_KINDS, Effect, Param
from hds.effects.body import MassScale
from hds.effects.force_terms import JointForceTerms
from hds.effects.friction import (
    BreakawayFriction,
    CoulombFriction,
    QuadraticDrag,
    ViscousDamping,
)
from hds.effects.inertial import ComScale, InertiaScale
from hds.effects.lab import LAB_EFFECTS
from hds.effects.sensor import SensorBias

LIBRARY: dict[str, Effect] = {}


def register(effect: Effect) -> Effect:
    """Add an effect to the library under its name (configs, simulators, plants and
    discovery then know it); returns it."""
    what = type(effect).__name__
    required = ("name", "target_kind", "description", "physical_name", "params", "stage")
    missing = [a for a in required if not hasattr(effect, a)]
    if missing:
        raise ValueError(f"effect {what} lacks {missing}; set them as class attributes")
    if effect.stage not in STAGES or effect.target_kind not in TARGET_KINDS:
        raise ValueError(
            f"effect {what}: stage {effect.stage!r} must be one of {list(STAGES)} and "
            f"target_kind {effect.target_kind!r} one of {list(TARGET_KINDS)}"
        )
    if not effect.params or not all(isinstance(p, Param) for p in effect.params):
        raise ValueError(f"effect {what}: params must be a tuple of hds.effects.Param")
    if effect.name in LIBRARY:
        raise ValueError(f"effect '{effect.name}' is registered already; give it another name")
    LIBRARY[effect.name] = effect
    return effect


register(CoulombFriction())
register(ViscousDamping())
register(QuadraticDrag())
register(BreakawayFriction())
register(ActuatorGain())
register(ActuatorOffset())
register(ActuatorDeadzone())
register(ActionDelay())
register(ActuatorLag())
register(MassScale())
register(ComScale())
register(InertiaScale())
register(SensorBias())
register(JointForceTerms())
for _lab_effect in LAB_EFFECTS:  # the lab plants' effects: no candidates of discovery's
    register(_lab_effect())


def candidate_effects() -> list[str]:
    """The effects gap discovery fits as candidates (the generic force terms it fits apart)."""
    return [name for name, effect in LIBRARY.items() if effect.candidate]


def default_candidates() -> list[str]:
    """discover.effects' default: the candidates not marked opt-in (`default_candidate`)."""
    return [name for name in candidate_effects() if LIBRARY[name].default_candidate]


def effect_type(name: str) -> Effect:
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
