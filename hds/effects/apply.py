"""Effects placed on a model, applied inside the differentiable simulator.

An `EffectSet` is the static part (which effect acts where, and integer parameters such as a
delay's length); its continuous parameters travel separately as a pytree (`EffectParams`), so
they can be differentiated (gap discovery), vmapped (friction-gap sweeps) or scaled.

Stages, in the order a step applies them:
  system   mass_scale, actuator_gain          edit the brax System
  command  action_delay, deadzone, offset     once per environment step, on the control
  substep  actuator_lag, coulomb, viscous     every physics substep (filter state, joint forces)
  observe  sensor_bias                        on the observation
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp

from hds.effects.library import FRICTION_EFFECTS, check_params, effect_type

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
    steps: int = 0  # action_delay only: static, it sets the buffer length


@dataclass(frozen=True)
class EffectSet:
    sites: tuple[Site, ...] = ()

    def __len__(self) -> int:
        return len(self.sites)

    def of(self, *names: str):
        return [(i, s) for i, s in enumerate(self.sites) if s.name in names]

    # -- state carried by stateful effects (delay buffers, lag filters) --
    def init_state(self) -> dict:
        state = {}
        for i, s in self.of("action_delay"):
            state[f"delay{i}"] = jnp.zeros((s.steps,))
        for i, _ in self.of("actuator_lag"):
            state[f"lag{i}"] = jnp.zeros(())
        return state

    def modify_system(self, params: EffectParams, sys):
        for i, s in self.of("mass_scale"):
            scale = params[i]["scale"]
            inertia = sys.link.inertia
            inertia = inertia.replace(
                mass=inertia.mass.at[s.index].multiply(scale),
                i=inertia.i.at[s.index].multiply(scale),
            )
            sys = sys.replace(link=sys.link.replace(inertia=inertia))
            if hasattr(sys, "body_mass"):  # the mjx backend reads MuJoCo's own fields
                sys = sys.replace(
                    body_mass=sys.body_mass.at[s.index + 1].multiply(scale),
                    body_inertia=sys.body_inertia.at[s.index + 1].multiply(scale),
                )
        for i, s in self.of("actuator_gain"):
            gain = params[i]["gain"]
            sys = sys.replace(
                actuator=sys.actuator.replace(gear=sys.actuator.gear.at[s.index].multiply(gain))
            )
            if hasattr(sys, "actuator_gear"):
                sys = sys.replace(actuator_gear=sys.actuator_gear.at[s.index, 0].multiply(gain))
        return sys

    def command(self, params: EffectParams, state: dict, u: jax.Array, sharpness: float | None):
        """Transform the control given at an environment step; returns (control, state)."""
        state = dict(state)
        for i, s in self.of("action_delay"):
            buf = state[f"delay{i}"]
            if s.steps > 0:
                state[f"delay{i}"] = jnp.concatenate([buf[1:], u[s.index][None]])
                u = u.at[s.index].set(buf[0])
        for i, s in self.of("actuator_deadzone"):
            half = 0.5 * params[i]["width"]
            u = u.at[s.index].set(u[s.index] - _clip(u[s.index], half, sharpness))
        for i, s in self.of("actuator_offset"):
            u = u.at[s.index].add(params[i]["offset"])
        return u, state

    def substep(self, params, state: dict, u, qd, h: float, sharpness, gradient_sharpness=None):
        """One physics substep: (applied control, joint forces [nqd], next state).
        `gradient_sharpness`: see `friction_direction`."""
        state = dict(state)
        for i, s in self.of("actuator_lag"):
            y = state[f"lag{i}"]
            tau = jnp.maximum(params[i]["time_constant"], 1e-6)
            y = y + (1.0 - jnp.exp(-h / tau)) * (u[s.index] - y)
            # The force uses the updated output (MuJoCo's actearly), so a time constant of 0
            # passes the control through unchanged: the effect's nominal value is a no-op.
            state[f"lag{i}"] = y
            u = u.at[s.index].set(y)
        force = jnp.zeros_like(qd)
        for i, s in self.of("coulomb_friction"):
            direction = friction_direction(qd[s.index], sharpness, gradient_sharpness)
            force = force.at[s.index].add(-params[i]["force"] * direction)
        for i, s in self.of("viscous_damping"):
            force = force.at[s.index].add(-params[i]["coefficient"] * qd[s.index])
        return u, force, state

    def observe(self, params: EffectParams, obs: jax.Array) -> jax.Array:
        for i, s in self.of("sensor_bias"):
            obs = obs.at[s.index].add(params[i]["bias"])
        return obs


def friction_direction(v, sharpness, gradient_sharpness=None):
    """The direction of dry friction: sign(v) when `sharpness` is None, else tanh(k v). With
    `gradient_sharpness` k_g, the value of tanh(k v) and the gradient of tanh(k_g v) (a
    surrogate gradient): a sharp law sticks like the plant's, but its gradient at rest is
    nearly zero (a small push does not move a stuck cart), which leaves a policy that starts
    inside the friction nothing to learn from; a softer law's gradient says how a larger
    push moves it."""
    if sharpness is None:
        return jnp.sign(v)
    direction = jnp.tanh(sharpness * v)
    if gradient_sharpness is None:
        return direction
    surrogate = jnp.tanh(gradient_sharpness * v)
    return surrogate + jax.lax.stop_gradient(direction - surrogate)


def _clip(u, half, sharpness):
    """clip(u, -half, half); a softplus-smoothed version when sharpness is given."""
    if sharpness is None:
        return jnp.clip(u, -half, half)
    sp = jax.nn.softplus
    return (sp(sharpness * (u + half)) - sp(sharpness * (u - half))) / sharpness - half


def as_spec(spec) -> EffectSpec:
    """An EffectSpec from a dict or from anything with name, target and params (EffectConfig)."""
    if isinstance(spec, EffectSpec):
        return spec
    if isinstance(spec, dict):
        return EffectSpec(spec["name"], spec["target"], dict(spec.get("params", {})))
    return EffectSpec(spec.name, spec.target, dict(spec.params))


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
        checked.append((spec, check_params(spec.name, dict(spec.params), where=spec.key)))
    return checked


def place(
    specs, names: dict[str, dict[str, int]], friction_gap: float = 1.0
) -> tuple[EffectSet, EffectParams]:
    """Resolve effect specs against a model's names (checked by `check`); `friction_gap`
    scales the friction effects' magnitudes."""
    sites, params = [], []
    for spec, values in check(specs, names):
        if spec.name in FRICTION_EFFECTS:
            values[FRICTION_EFFECTS[spec.name]] *= friction_gap
        index = names[effect_type(spec.name).target_kind][spec.target]
        sites.append(Site(spec.name, spec.target, index, int(values.pop("steps", 0))))
        params.append({k: jnp.asarray(v, jnp.float32) for k, v in values.items()})
    return EffectSet(tuple(sites)), tuple(params)
