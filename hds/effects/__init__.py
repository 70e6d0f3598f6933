"""A library of named, parametric physical effects that compose onto a system's step."""

from hds.effects.apply import EffectParams, EffectSet, EffectSpec, place
from hds.effects.library import LIBRARY, EffectType, Param, check_params, effect_type

__all__ = [
    "LIBRARY",
    "EffectParams",
    "EffectSet",
    "EffectSpec",
    "EffectType",
    "Param",
    "check_params",
    "effect_type",
    "place",
]
