"""A library of named, parametric physical effects that compose onto a system's step.

Each effect is one object (`Effect`, hds.effects.base) holding its parameters, its
differentiable law, the C MuJoCo plant's exact law and what gap discovery needs; the
library (`LIBRARY`) is their registry: a new effect is one file and `register(MyEffect())`.
"""

from hds.effects.apply import EffectParams, EffectSet, EffectSpec, place
from hds.effects.base import Effect, Param
from hds.effects.library import LIBRARY, check_params, effect_type, register

__all__ = [
    "LIBRARY",
    "Effect",
    "EffectParams",
    "EffectSet",
    "EffectSpec",
    "Param",
    "check_params",
    "effect_type",
    "place",
    "register",
]
