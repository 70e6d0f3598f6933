"""The model gap discovery works on: the simulator carrying every candidate effect at once.

Every effect of the library is an exact no-op at its nominal value, so the simulator is built
once with a SUPERSET: the effects the env already models (fixed at their configured values)
plus every candidate (effect type x place it can act on) at its nominal value. A flat vector
`theta` holds the candidates' continuous parameters; a candidate is "off" when its entries sit
at their nominal values, so every subset of candidates is one and the same compiled function
with different numbers. Action delays (a static buffer length in `hds.effects.apply`) are done
here instead, by shifting the measured actions (zeros before an episode starts, as a plant's
empty delay buffer gives): the delay is an integer argument, enumerated without recompiling.

Predictions are k-step "windows": the simulator starts from a measured observation (minus the
sensor biases of theta, i.e. the true state the biased sensor saw), replays the measured
actions for k steps and is compared with the measured observations. Before a window starts,
the `warmup` preceding actions are replayed through the stateful effects (action delay
buffers, actuator lag filters) so they hold what the plant's held at that time.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from hds.effects.apply import as_spec
from hds.effects.base import ACTUATOR, JOINT, OBSERVATION
from hds.effects.library import effect_type
from hds.envs.system import make_simulator


@dataclass(frozen=True)
class Candidate:
    """One effect at one place: continuous parameters at `slots` of theta, or a delay."""

    name: str
    target: str
    slots: tuple[int, ...] = ()
    params: tuple[str, ...] = ()
    actuator: int = -1  # an effect that shifts actions (a delay): the actuator's index
    steps: int = 0  # ... and the shift, environment steps

    @property
    def key(self) -> str:
        return f"{self.name}@{self.target}"

    @property
    def shifts_actions(self) -> bool:
        return effect_type(self.name).shifts_actions

    @property
    def label(self) -> str:
        return f"{self.key}={self.steps}" if self.shifts_actions else self.key


def _unit(name: str, param: str, kind: str, target: str, joint_type: dict, obs_unit: dict) -> str:
    unit = effect_type(name).param(param).unit
    if kind == JOINT and " or " in unit:  # "N or N m": slide joints take the first
        slide, hinge = unit.split(" or ")
        return slide if joint_type[target] == "slide" else hinge
    if kind == OBSERVATION and unit == "observation units":
        return obs_unit[target]
    return unit


@dataclass(frozen=True, eq=False)
class Model:
    """The superset simulator and the layout of theta; hashable by identity (jit closes over)."""

    sim: object  # hds.envs.system.Simulator
    base: tuple  # the superset's effect parameters: env effects fixed, candidates nominal
    where: tuple  # per site: {param: slot} for candidates, {} for the env's own effects
    candidates: tuple[Candidate, ...]  # continuous ones first, then delays
    nominal: np.ndarray  # [N] theta with every candidate off
    start: np.ndarray  # [N] value a parameter starts from when its candidate is switched on
    lower: np.ndarray  # [N]
    upper: np.ndarray  # [N]
    units: tuple[str, ...]  # [N]
    env_effects: tuple  # EffectSpecs the simulator already models
    max_delay: int
    warmup: int

    @property
    def n_theta(self) -> int:
        return len(self.nominal)

    @property
    def pad(self) -> int:
        """Zero actions stored before every episode: the warm-up and the longest delay."""
        return self.warmup + self.max_delay

    def params(self, theta: jax.Array) -> tuple:
        """The simulator's effect parameters for theta."""
        out = []
        for site_params, slots in zip(self.base, self.where, strict=True):
            out.append({k: (theta[slots[k]] if k in slots else v) for k, v in site_params.items()})
        return tuple(out)

    # -- predictions ------------------------------------------------------------------------

    def window(self, params, obs0, u_warm, u):
        """Predicted observations [k, n_obs] after each of the actions u [k, n_act], from the
        measured observation obs0, the stateful effects warmed up on u_warm [warmup, n_act]."""
        sim = self.sim
        effects = sim.effects
        lo, hi = jnp.asarray(sim.ctrl_range[:, 0]), jnp.asarray(sim.ctrl_range[:, 1])
        zeros_q, zeros_qd = jnp.zeros(sim.nq), jnp.zeros(sim.n_obs - sim.nq)

        def warm(est, ut):
            ut, est = effects.command(params, est, ut, sim.sharpness)
            ut = jnp.clip(ut, lo, hi)
            for _ in range(sim.frames):
                _, _, est = effects.substep(
                    params, est, ut, zeros_q, zeros_qd, sim.timestep, sim.sharpness
                )
            return est, None

        est = effects.init_state()
        if est and u_warm.shape[0] > 0:
            est, _ = jax.lax.scan(warm, est, u_warm)
        x0 = obs0 - effects.observe(params, jnp.zeros_like(obs0))  # the sensors' biases off
        state = sim.init(x0[: sim.nq], x0[sim.nq :], params).replace(effects=est)

        def step(state, ut):
            state = sim.step(params, state, ut)
            return state, sim.observe(params, state)

        return jax.lax.scan(step, state, u)[1]

    def predict(self, theta, delay, obs, acts, episode, start, k: int, shift=None):
        """[W, k, n_obs] predictions of W windows (episode [W], start [W]) of the stacked data
        obs [E, T+1, n_obs] and zero-padded actions acts [E, pad + T, n_act]. `shift` [W, n_obs]
        moves each window's initial state away from its measurement (estimated states)."""
        params = self.params(theta)
        n_act = acts.shape[-1]
        offsets = jnp.arange(self.warmup + k)[:, None] - delay[None, :]  # [warmup + k, n_act]
        if shift is None:
            shift = jnp.zeros((episode.shape[0], obs.shape[-1]), obs.dtype)

        def one(e, t, dx):
            rows = self.max_delay + t + offsets  # pad - warmup + t + j - delay
            u = acts[e][rows, jnp.arange(n_act)[None, :]]
            return self.window(params, obs[e, t] + dx, u[: self.warmup], u[self.warmup :])

        return jax.vmap(one)(episode, start, shift)

    def residuals(self, theta, delay, data, k: int, z=None):
        """Normalized residuals [W, k, n_obs] (zero on padded windows): prediction minus
        measurement, hinge angles wrapped, each variable divided by its scale. `z` [W, n_obs]:
        each window's initial state minus its measurement, in units of scale."""
        obs, acts, episode, start, mask, scale = data
        shift = None if z is None else z * scale
        pred = self.predict(theta, delay, obs, acts, episode, start, k, shift)
        idx = start[:, None] + 1 + jnp.arange(k)[None, :]
        target = obs[episode[:, None], idx]  # [W, k, n_obs]
        err = pred - target
        angular = np.zeros(self.sim.n_obs, dtype=bool)
        angular[: self.sim.nq] = self.sim.angular
        err = jnp.where(angular, jnp.arctan2(jnp.sin(err), jnp.cos(err)), err)
        err = jnp.where(jnp.isfinite(err), err, 1e3)  # a diverged prediction is a large error
        return err / scale * mask[:, None, None]


def candidate_specs(sim, effects: list[str], existing: set[str]) -> list[tuple[str, str]]:
    """(effect, target) of every candidate: each effect type on every place of its kind."""
    out = []
    for name in effects:
        kind = effect_type(name).target_kind
        for target in sim.targets[kind]:
            if f"{name}@{target}" not in existing:
                out.append((name, target))
    return out


def build_model(env_cfg, dt: float, effects: list[str], max_delay: int, warmup: int) -> Model:
    """The superset model of an `env` config for data sampled every dt seconds."""
    env_effects = [as_spec(e) for e in env_cfg.effects]
    probe, _ = make_simulator(
        env_cfg.xml, backend=env_cfg.backend, timestep=env_cfg.timestep, effects=env_effects
    )
    frames = round(dt / probe.timestep)
    existing = {e.key for e in env_effects}
    continuous = [
        (n, t)
        for n, t in candidate_specs(probe, effects, existing)
        if not effect_type(n).shifts_actions
    ]
    specs = env_effects + [{"name": n, "target": t, "params": {}} for n, t in continuous]
    sim, base = make_simulator(
        env_cfg.xml,
        backend=env_cfg.backend,
        timestep=env_cfg.timestep,
        frames=frames,
        effects=specs,
        sharpness=env_cfg.sharpness,
    )
    joint_type = {
        sim.obs_names[i][2:]: ("hinge" if sim.angular[i] else "slide") for i in range(sim.nq)
    }
    obs_unit = {
        n: ("rad" if joint_type.get(n.split("_", 1)[-1]) == "hinge" else "m")
        + ("/s" if n.startswith("qd_") else "")
        for n in sim.obs_names
    }

    where, candidates, nominal, start, lower, upper, units = [], [], [], [], [], [], []
    n_env = len(env_effects)
    for i, site in enumerate(sim.effects.sites):
        if i < n_env:
            where.append({})
            continue
        slots = {}
        etype = effect_type(site.name)
        for p in etype.params:
            slots[p.name] = len(nominal)
            lo, hi = p.fit_bounds or (p.lower, p.upper)
            nominal.append(p.nominal)
            start.append(p.nominal + p.fit_start_in_timesteps * sim.timestep)
            lower.append(lo)
            upper.append(hi)
            units.append(
                _unit(site.name, p.name, etype.target_kind, site.target, joint_type, obs_unit)
            )
        where.append(slots)
        candidates.append(Candidate(site.name, site.target, tuple(slots.values()), tuple(slots)))
    for name in (n for n in effects if effect_type(n).shifts_actions):
        (param,) = (p.name for p in effect_type(name).params)
        for target, a in sim.targets[ACTUATOR].items():
            if f"{name}@{target}" in existing:
                continue
            candidates += [
                Candidate(name, target, params=(param,), actuator=a, steps=s)
                for s in range(1, max_delay + 1)
            ]
    return Model(
        sim=sim,
        base=base,
        where=tuple(where),
        candidates=tuple(candidates),
        nominal=np.array(nominal, np.float32),
        start=np.array(start, np.float32),
        lower=np.array(lower, np.float32),
        upper=np.array(upper, np.float32),
        units=tuple(units),
        env_effects=tuple(env_effects),
        max_delay=int(max_delay),
        warmup=int(warmup),
    )
