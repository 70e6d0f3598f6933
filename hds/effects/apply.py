"""Effects placed on a model, applied inside the differentiable simulator.

An `EffectSet` is the static part (which effect acts where, and integer parameters such as a
delay's length); its continuous parameters travel separately as a pytree (`EffectParams`), so
they can be differentiated (gap discovery), vmapped (friction-gap sweeps) or scaled.

A step applies each effect at its stage (hds.effects.base), in the order of the stages:
  system   edit the brax System (mass_scale, actuator_gain)
  command  once per environment step, on the control (action_delay, deadzone, offset)
  substep  every physics substep: filter states, joint forces (actuator_lag, friction)
  observe  on the observation (sensor_bias)
Each effect's law is its own (`hds.effects.library`); this module only places and orders them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp

from hds.effects.base import COMMAND, JOINT, OBSERVE, SUBSTEP, SYSTEM
from hds.effects.library import check_params, effect_type

EffectParams = tuple  # one {param: array} dict per placed effect, aligned with EffectSet.sites


@dataclass(frozen=True)
class EffectSpec:
    """An effect as a user names it: library name, target name, parameter values."""

    name: str
    target: str
    params: dict[str, float] = field(default_factory=dict, hash=False, compare=False)

    @property
    def key(self) -> str:
        return f"{self.name}@{self.target}"


@dataclass(frozen=True)
class Site:
    name: str
    target: str
    index: int  # dof for joints, actuator, brax link (body id - 1), observation index
    discrete: tuple[tuple[str, int], ...] = ()  # static: they set shapes (a delay's buffer)
    # a joint's inverse inertia at the model's reference pose (MuJoCo's dof_invweight0): the
    # speed one unit of impulse on its dof gives it; 0 where unknown or not a joint
    mobility: float = 0.0

    def static(self, param: str) -> int:
        return dict(self.discrete)[param]


@dataclass(frozen=True)
class EffectSet:
    sites: tuple[Site, ...] = ()

    def __len__(self) -> int:
        return len(self.sites)

    def at(self, stage: str):
        """(index, site, effect) of the effects acting at `stage`, in the order they act."""
        placed = [(i, s, effect_type(s.name)) for i, s in enumerate(self.sites)]
        return sorted(
            [row for row in placed if row[2].stage == stage], key=lambda row: row[2].order
        )

    def init_state(self) -> dict:
        """The states of stateful effects (delay buffers, lag filters), by site index."""
        return _stateful({i: effect_type(s.name).init_state(s) for i, s in enumerate(self.sites)})

    def modify_system(self, params: EffectParams, sys):
        for i, site, effect in self.at(SYSTEM):
            sys = effect.modify_system(site, params[i], sys)
        return sys

    def command(self, params: EffectParams, state: dict, u: jax.Array, sharpness: float | None):
        """Transform the control given at an environment step; returns (control, state)."""
        state = dict(state)
        for i, site, effect in self.at(COMMAND):
            u, state[i] = effect.command(site, params[i], state.get(i), u, sharpness)
        return u, _stateful(state)

    def substep(self, params, state: dict, u, q, qd, h: float, sharpness, gradient_sharpness=None):
        """One physics substep at joint positions q and velocities qd: (applied control, joint
        forces [nqd], next state). `gradient_sharpness`: see
        `hds.effects.friction.friction_direction`."""
        state = dict(state)
        force = jnp.zeros_like(qd)
        for i, site, effect in self.at(SUBSTEP):
            u, force, state[i] = effect.substep(
                site, params[i], state.get(i), u, force, q, qd, h, sharpness, gradient_sharpness
            )
        return u, force, _stateful(state)

    def observe(self, params: EffectParams, obs: jax.Array) -> jax.Array:
        for i, site, effect in self.at(OBSERVE):
            obs = effect.observe(site, params[i], obs)
        return obs


def _stateful(state: dict) -> dict:
    return {i: x for i, x in state.items() if x is not None}


def as_spec(spec) -> EffectSpec:
    """An EffectSpec from a dict or from anything with name, target and params (EffectConfig)."""
    if isinstance(spec, EffectSpec):
        return spec
    if isinstance(spec, dict):
        return EffectSpec(spec["name"], spec["target"], dict(spec.get("params", {})))
    return EffectSpec(spec.name, spec.target, dict(spec.params))


def at_friction_gap(name: str, values: dict, friction_gap: float) -> dict:
    """An effect's parameters with its friction magnitude (if it has one) scaled by
    `friction_gap` (real.friction_gap): the values a plant applies."""
    friction = effect_type(name).friction
    if not friction or friction not in values:
        return dict(values)
    return {**values, friction: values[friction] * friction_gap}


def applied(specs, friction_gap: float = 1.0) -> list[dict]:
    """Effect specs as JSON with the values a plant or simulator applies: every parameter
    (defaults filled in), friction magnitudes scaled by `friction_gap`."""
    out = []
    for spec in map(as_spec, specs):
        values = check_params(spec.name, dict(spec.params), where=spec.key)
        values = at_friction_gap(spec.name, values, friction_gap)
        params = {k: v if isinstance(v, int) else float(v) for k, v in values.items()}
        out.append({"name": spec.name, "target": spec.target, "params": params})
    return out


def check(specs, names: dict[str, dict[str, int]]) -> list[tuple[EffectSpec, dict[str, float]]]:
    """Check effect specs against a model's names: each effect exists, acts on a target of its
    kind that the model has, is given once and has valid parameters. Returns (spec, complete
    parameters) pairs. Pure Python: `hds.config.validate` calls it before anything compiles.

    `names` maps each target kind (joint, actuator, body, observation) to {name: index} of the
    model's targets of that kind (hds.envs.system.target_names).
    """
    checked, seen = [], set()
    for spec in specs:
        spec = as_spec(spec)
        etype = effect_type(spec.name)
        allowed = list(names[etype.target_kind])
        if spec.target not in allowed:
            raise ValueError(
                f"effect '{spec.name}' acts on a {etype.target_kind}, and this model has no "
                f"{etype.target_kind} '{spec.target}'; choose one of {allowed}"
            )
        if spec.key in seen:
            raise ValueError(f"effect '{spec.key}' is given twice; give each effect once")
        seen.add(spec.key)
        values = check_params(spec.name, dict(spec.params), where=spec.key)
        etype.check_site(spec.target, values, names, spec.key)
        checked.append((spec, values))
    return checked


def place(
    specs, names: dict[str, dict[str, int]], friction_gap: float = 1.0, dof_mobility=None
) -> tuple[EffectSet, EffectParams]:
    """Resolve effect specs against a model's names (checked by `check`); `friction_gap`
    scales the friction effects' magnitudes; `dof_mobility`: each dof's inverse inertia
    (`Site.mobility`), if known."""
    sites, params = [], []
    for spec, values in check(specs, names):
        effect = effect_type(spec.name)
        values = at_friction_gap(spec.name, values, friction_gap)
        index = names[effect.target_kind][spec.target]
        discrete = tuple((p.name, int(values.pop(p.name))) for p in effect.params if p.discrete)
        mobility = 0.0
        if effect.target_kind == JOINT and dof_mobility is not None:
            mobility = float(dof_mobility[index])
        sites.append(Site(spec.name, spec.target, index, discrete, mobility))
        params.append({k: jnp.asarray(v, jnp.float32) for k, v in values.items()})
    return EffectSet(tuple(sites)), tuple(params)
