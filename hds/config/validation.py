"""Validation of a composed config: `validate(cfg)` builds the typed config (hds.config.schemas)
and runs every check before anything compiles: each schema's `check()`, no unknown key, finite
numbers, the effects against the model's names, and the memory a training program needs
(hds.config.model, which compiles the MJCF and asks JAX for the device: imported only when a
config is validated). `check_override_keys` refuses a command line's unknown keys before Hydra
composes.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing

from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue

from hds.config.schemas import Config, DRConfig, EnvConfig, RealConfig


def _check_all(node) -> None:
    """Run `check` on every schema in the tree (they cannot be __post_init__: OmegaConf builds
    default instances of the schemas, with missing values, while it composes)."""
    if hasattr(node, "check"):
        node.check()
    if isinstance(node, dict):
        children = node.values()
    elif isinstance(node, list):
        children = node
    else:
        children = getattr(node, "__dict__", {}).values()
    for child in children:
        if isinstance(child, list | dict) or hasattr(child, "__dataclass_fields__"):
            _check_all(child)


def _check_effect_targets(config) -> None:
    """Check that env.xml exists, and env.effects and real.effects against its names (the
    model both the simulator and the plants are built from), with the check the builders run
    (hds.effects.apply.check). Compiling the MJCF with MuJoCo takes milliseconds and compiles
    nothing with JAX; it is skipped when no effect is given."""
    from hds.config.model import effect_targets, resolve_xml
    from hds.effects.apply import EffectSpec, check

    env = getattr(config, "env", None)
    if not isinstance(env, EnvConfig):
        return
    real = getattr(config, "real", None)
    groups = [("env.effects", env.effects)]
    if isinstance(real, RealConfig):
        groups.append(("real.effects", real.effects))
    for key, plant in getattr(config, "eval_plants", {}).items():
        groups.append((f"eval_plants.{key}.effects", plant.effects))
    dr = getattr(config, "dr", None)
    if isinstance(dr, DRConfig):
        ranged = [EffectSpec(e.name, e.target) for e in dr.effects]
        groups.append(("dr.effects", [*env.effects, *ranged]))  # none given twice
    try:
        xml = str(resolve_xml(env.xml))
    except FileNotFoundError as err:
        raise ValueError(f"env.xml: {err}") from None
    if isinstance(real, RealConfig) and real.family:
        from hds.real.lab import check_env

        check_env(real.family, xml)
    if not any(effects for _, effects in groups):
        return
    names = effect_targets(xml)
    for key, effects in groups:
        try:
            check(effects, names)
        except ValueError as err:
            raise ValueError(f"{key}: {err}") from None


def validate(cfg: DictConfig, check_memory: bool = True) -> Config:
    """Build the typed config and run every range check; raise ValueError naming the key.
    `check_memory=False` skips the check against this machine's device memory (a sweep's jobs
    checked before their launch, which may run them on other devices)."""
    try:
        _check_known_keys(cfg)
    except ValueError as err:
        raise ValueError(f"invalid config: {err}") from None
    try:
        config = OmegaConf.to_object(cfg)
    except MissingMandatoryValue as err:  # a required value left as ???
        raise ValueError(
            f"invalid config: {err.full_key} has no value (???): give it, {err.full_key}=<value>"
            + (" (an MJCF file's path)" if err.full_key == "env.xml" else "")
        ) from None
    except Exception as err:
        raise ValueError(f"invalid config: {err}") from None
    try:
        _check_finite_numbers(OmegaConf.to_container(cfg, resolve=True))
        _check_all(config)
        _check_effect_targets(config)
        if check_memory:
            from hds.config.model import check_memory as check_device_memory

            check_device_memory(config)
    except ValueError as err:
        raise ValueError(f"invalid config: {err}") from None
    return config


FLOAT32_MAX = 3.4028234663852886e38  # numpy.finfo(numpy.float32).max, without importing numpy


def _check_finite_numbers(node, where: str = "") -> None:
    """Refuse NaN and inf anywhere, and numbers beyond float32 (inf once in an array): no
    setting means anything at them (an infinite friction gap or noise scale passes every range
    check, and its results are meaningless)."""
    if isinstance(node, float) and not math.isfinite(node):
        raise ValueError(f"{where} = {node} is not a finite number; give a finite value")
    if isinstance(node, int | float) and not isinstance(node, bool) and abs(node) > FLOAT32_MAX:
        # every number ends up in float32 arrays, where it would be inf
        raise ValueError(
            f"{where} = {node} is beyond float32's range (+-{FLOAT32_MAX:.4g}), in which the "
            "simulator and the policy compute; give a smaller value"
        )
    if isinstance(node, dict):
        for key, child in node.items():
            _check_finite_numbers(child, f"{where}.{key}" if where else str(key))
    elif isinstance(node, list):
        for i, child in enumerate(node):
            _check_finite_numbers(child, f"{where}[{i}]")


def _unknown_key(where: str, key, allowed: list[str]) -> str:
    close = difflib.get_close_matches(str(key), allowed, n=1)
    hint = f"; did you mean '{close[0]}'?" if close else ""
    where = where or "the config"
    return f"{where} has no key '{key}'; its keys are: {', '.join(allowed)}{hint}"


def _child_type(annotation, key: str):
    """The schema of `key` below a node of type `annotation`: a dataclass to check further,
    or None where anything goes (dicts, numbers)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is list and args:
        return args[0] if key.isdigit() else None
    if dataclasses.is_dataclass(annotation):
        hints = typing.get_type_hints(annotation)
        return hints.get(key, _UNKNOWN)
    return None


_UNKNOWN = object()


def check_override_keys(overrides, schema: type, groups=()) -> None:
    """Refuse command-line overrides of keys the schema does not have, naming the keys it
    allows there and the closest one, before Hydra composes anything. `groups`: the config
    groups of conf/ (env, method, ...), which are keys too. Overrides forced in with `+` are
    checked at validation (`_check_known_keys`)."""
    for override in OverridesParser.create().parse_overrides([str(o) for o in overrides]):
        path = override.key_or_group
        if override.is_add() or override.is_delete() or "/" in path or path.startswith("hydra"):
            continue
        if override.is_force_add() or path in groups:
            continue
        node, where = schema, ""
        for key in path.split("."):
            child = _child_type(node, key)
            if child is _UNKNOWN:
                allowed = [f.name for f in dataclasses.fields(node)]
                if not where:
                    allowed += [g for g in groups if g not in allowed]
                raise ValueError(f"invalid config: {_unknown_key(where, key, allowed)}")
            if child is None:
                break
            node, where = child, f"{where}.{key}" if where else key


def _check_known_keys(node, where: str = "") -> None:
    """Refuse keys a schema does not have that composition let through (an override forced
    in with `+`, e.g. `+env.frictoin=1`, which OmegaConf.to_object would silently drop)."""
    if isinstance(node, DictConfig):
        schema = OmegaConf.get_type(node)
        keys = [str(k) for k in node.keys()]
        if dataclasses.is_dataclass(schema):
            allowed = [f.name for f in dataclasses.fields(schema)]
            extra = [k for k in keys if k not in allowed]
            if extra:
                raise ValueError(_unknown_key(where, extra[0], allowed))
    elif isinstance(node, ListConfig):
        keys = list(range(len(node)))
    else:
        return
    for key in keys:
        if OmegaConf.is_missing(node, key) or OmegaConf.is_interpolation(node, key):
            continue
        _check_known_keys(node[key], f"{where}.{key}" if where else str(key))
