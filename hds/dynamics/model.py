"""Learned dynamics models as engines for the trainer.

A model's state is the observation vector [q..., qd...] (for the systems of hds.envs the
observation is the full state), so `observe` and `qqd` just read it. One step is

  next = base(obs, u) + mean_k delta_k(obs, u)

  mlp       base = obs (the network predicts the change over one step), one member
  ensemble  base = obs, K members trained independently; their spread is the disagreement
  residual  base = the simulator's step from (q, qd) = obs with the env's effect parameters;
            the network predicts what the simulator gets wrong. With a zero correction the
            model is exactly the simulator. Its state is the observation, then the base's
            effect states (an actuator lag's filter), then its action delays' buffers (the
            last commanded controls, oldest first): the delays are the model's own, and the
            base and the network see the control the delay applies, so a delay named by
            discovery carries over from step to step (fitted on the recorded controls
            shifted as discovery shifts them: zeros before an episode), and so does a lag's
            filter (on recorded episodes, the filter where the controls before each state
            left it: `with_effect_states`). A rollout starts them at rest, as the simulator;
            a branch from a visited state starts its filters at rest too (its delays get the
            controls commanded before it).

delta_k = y_mean + y_std * net_k((features(obs) ++ u - x_mean) / x_std): inputs and outputs are
normalised with statistics of the training data. Hinge angles enter as (sin, cos) and their
one-step change is wrapped to [-pi, pi), so the model does not care about turn counts.
Every function here is pure JAX: usable inside jit, vmap and grad (w.r.t. state and actions).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from hds.effects import effect_type
from hds.effects.apply import EffectSet
from hds.networks import features
from hds.utils.pytree import pytree_dataclass

KINDS = ("mlp", "ensemble", "residual")


class MLP(nn.Module):
    """The delta network: silu hidden layers, linear output (zero at init when `zero_last`)."""

    hidden: Sequence[int]
    out: int
    zero_last: bool = False

    @nn.compact
    def __call__(self, x):
        for width in self.hidden:
            x = nn.silu(nn.Dense(width)(x))
        init = nn.initializers.zeros if self.zero_last else nn.initializers.lecun_normal()
        return nn.Dense(self.out, kernel_init=init)(x)


@pytree_dataclass
class Normalizer:
    x_mean: jax.Array  # [n_in] network inputs: features(obs) ++ u
    x_std: jax.Array
    y_mean: jax.Array  # [n_obs] one-step change (or correction), physical units
    y_std: jax.Array

    @classmethod
    def fit(cls, x: np.ndarray, y: np.ndarray) -> Normalizer:
        def stats(a):
            mean, std = a.mean(0), a.std(0)
            return (
                jnp.asarray(mean, jnp.float32),
                jnp.asarray(np.where(std > 1e-6, std, 1.0), jnp.float32),
            )

        return cls(*stats(x), *stats(y))

    @classmethod
    def identity(cls, n_in: int, n_out: int) -> Normalizer:
        return cls(jnp.zeros(n_in), jnp.ones(n_in), jnp.zeros(n_out), jnp.ones(n_out))

    def as_dict(self) -> dict:
        return {
            "x_mean": self.x_mean,
            "x_std": self.x_std,
            "y_mean": self.y_mean,
            "y_std": self.y_std,
        }


def wrap_angles(delta: jax.Array, angular: np.ndarray) -> jax.Array:
    """Wrap the hinge entries of a state difference [..., nq + nv] to [-pi, pi)."""
    mask = np.zeros(delta.shape[-1], dtype=bool)
    mask[: len(angular)] = angular
    wrapped = jnp.mod(delta + jnp.pi, 2 * jnp.pi) - jnp.pi
    return jnp.where(mask, wrapped, delta)


@dataclass(frozen=True, eq=False)
class DynamicsModel:
    """A fitted model; hashable by identity, so jit can close over it. `params` are stacked
    over members (leading axis K, K = 1 for mlp and residual)."""

    kind: str
    net: MLP
    params: Any
    norm: Normalizer
    obs_names: tuple[str, ...]
    action_names: tuple[str, ...]
    angular: np.ndarray  # hinge mask over q
    dt: float
    ctrl_range: np.ndarray  # [n_act, 2]
    task: Any = None  # where reset draws initial states from (env.task)
    sim: Any = None  # residual: the simulator whose step is corrected, less its action delays
    sim_params: Any = None  # residual: its effect parameters
    # residual: the simulator's action delays and their parameters, which the model applies
    # itself (`delayed`: the effects' own law), their buffers in its state after the observation
    delay_effects: EffectSet = EffectSet()
    delay_params: tuple = ()
    # residual: what a policy's gradient sees (dynamics.gradient). "model": the step's own
    # derivatives, the network's included; "simulator": the correction moves the states a
    # rollout visits, but its derivatives are dropped, so the gradient is the simulator's own
    # Jacobian along the corrected states (a fitted network's derivatives are not fitted)
    gradient: str = "model"

    @property
    def delays(self) -> tuple[tuple[int, int], ...]:
        """(action index, steps) of each action delay the model applies."""
        return tuple((s.index, s.static("steps")) for s in self.delay_effects.sites)

    @property
    def nq(self) -> int:
        return len(self.angular)

    @property
    def n_effect_state(self) -> int:
        """How many numbers the base's effect states hold (a lag's filter: one); 0 without."""
        if self.kind != "residual":
            return 0
        shapes = jax.eval_shape(self.sim.effects.init_state)  # no eager op: nothing compiles
        return int(sum(np.prod(leaf.shape, dtype=int) for leaf in jax.tree.leaves(shapes)))

    @property
    def n_carried(self) -> int:
        """The observation and the base's effect states: what `predict` maps to its next."""
        return self.n_obs + self.n_effect_state

    @property
    def n_obs(self) -> int:
        return len(self.obs_names)

    @property
    def n_act(self) -> int:
        return len(self.action_names)

    @property
    def history(self) -> int:
        """How many past controls the state holds (the longest delay; 0: the state is the
        observation)."""
        return max((steps for _, steps in self.delays), default=0)

    @property
    def members(self) -> int:
        return int(jax.tree.leaves(self.params)[0].shape[0])

    # -- the pieces of one step (single sample: obs [n_obs], u [n_act]) ------------------------

    def clip(self, u):
        return jnp.clip(u, self.ctrl_range[:, 0], self.ctrl_range[:, 1])

    def inputs(self, obs, u):
        """The network's input: the observation's features (of `obs`, or of its first
        n_obs entries, the rest the base's effect states) and the clipped control."""
        return jnp.concatenate([features(obs[: self.n_obs], self.angular), self.clip(u)], axis=-1)

    def base(self, obs, u):
        """What the network corrects: obs itself, or the simulator's next state (residual),
        from the effect states `obs` carries after the observation (at rest if it has none)
        and with theirs after the step."""
        if self.kind != "residual":
            return obs
        carried = obs[self.n_obs :] if obs.shape[-1] > self.n_obs else None
        nxt, after = _simulator_step(
            self.sim, self.nq, self.sim_params, self.ctrl_range, obs[: self.n_obs], carried, u
        )
        return nxt if carried is None else jnp.concatenate([nxt, after])

    def _padded(self, delta, like):
        """A correction of the observation, zeros for the effect states `like` carries."""
        extra = like.shape[-1] - self.n_obs
        return delta if not extra else jnp.concatenate([delta, jnp.zeros(extra, delta.dtype)])

    def with_effect_states(self, obs, applied) -> np.ndarray:
        """[E, T+1, n_carried]: recorded episodes `obs` [E, T+1, n_obs] with the base's effect
        states at each observation: at rest at the start, then the base's law run along the
        recorded states and the controls `applied` [E, T, n_act] (`applied_actions`). A lag's
        filter depends on the controls alone, so there it is the simulator's exactly. `obs`
        itself where the base has none. One program per base simulator and episode length,
        whatever the model's network or the number of episodes (`_effect_states_along`)."""
        if not self.n_effect_state:
            return obs
        obs, applied = np.asarray(obs, np.float32), np.asarray(applied, np.float32)
        ctrl_range = np.asarray(self.ctrl_range, np.float32)
        along = [
            _effect_states_along(self.sim, self.nq, self.sim_params, ctrl_range, o, u)
            for o, u in zip(obs, applied, strict=True)
        ]
        return np.concatenate([obs, np.stack(along)], axis=-1)

    def normalized_deltas(self, obs, u):
        """[K, n_obs] each member's output in normalised units."""
        x = (self.inputs(obs, u) - self.norm.x_mean) / self.norm.x_std
        return jax.vmap(lambda p: self.net.apply(p, x))(self.params)

    def deltas(self, obs, u):
        """[K, n_obs] each member's change (or correction) in physical units."""
        return self.norm.y_mean + self.norm.y_std * self.normalized_deltas(obs, u)

    def predict(self, obs, u):
        """The next observation: base plus the members' mean delta (its derivatives dropped
        where `gradient` is "simulator": the same value, the base's gradient)."""
        delta = jnp.mean(self.deltas(obs, u), axis=0)
        if self.gradient == "simulator":
            delta = jax.lax.stop_gradient(delta)
        return self.base(obs, u) + self._padded(delta, obs)

    def predict_members(self, obs, u):
        """[K, n_obs] every member's next observation."""
        return self.base(obs, u)[: self.n_obs] + self.deltas(obs, u)

    def disagreement(self, obs, u):
        """Spread of the members: std over members of the normalised delta, mean over outputs
        (0 for a single member). Large where the data did not pin the model down."""
        return jnp.mean(jnp.std(self.normalized_deltas(obs, u), axis=0))

    # -- action delays -------------------------------------------------------------------------

    def delayed(self, buffer, u):
        """(the control applied when `u` is commanded, the buffer after it), by the delays'
        own law (`hds.effects.apply.EffectSet.command`) on the buffers the state holds."""
        ends = np.cumsum([steps for _, steps in self.delays])[:-1]
        state = dict(enumerate(jnp.split(buffer, ends)))
        applied, state = self.delay_effects.command(self.delay_params, state, u, None)
        return applied, jnp.concatenate([state[i] for i in range(len(self.delays))])

    def applied_actions(self, actions: np.ndarray) -> np.ndarray:
        """[E, T, n_act] the controls applied when `actions` were commanded from the start of
        each episode: every delayed control `steps` later, zeros before (a buffer at rest, as
        the simulator's and the plant's start; discovery shifts the data the same way)."""
        if not self.delays:
            return actions
        out = np.array(actions, copy=True)
        for index, steps in self.delays:
            out[:, :steps, index] = 0.0
            out[:, steps:, index] = actions[:, :-steps, index]
        return out

    def start(self, obs, previous=None):
        """The model's state at observation `obs`: its effect states at rest, its delays'
        buffers at rest, or holding `previous` ([history, n_act]: the controls commanded
        before it, oldest first)."""
        if not self.delays and not self.n_effect_state:
            return obs
        buffers = [
            jnp.zeros(steps, obs.dtype) if previous is None else previous[-steps:, index]
            for index, steps in self.delays
        ]
        rest = _at_rest(self.sim)[0] if self.kind == "residual" else jnp.zeros(0)
        return jnp.concatenate([obs, rest.astype(obs.dtype), *buffers]).astype(obs.dtype)

    # -- the engine protocol ------------------------------------------------------------------

    def reset(self, key):
        if self.task is None:
            raise ValueError(
                "this model has no task to draw initial states from: load or fit it "
                "with an env (hds.dynamics.load(path, env))"
            )
        q, qd = self.task.initial(key)
        return self.start(jnp.concatenate([q, qd]).astype(jnp.float32))

    def step(self, state, u, params=None):
        buffered = sum(steps for _, steps in self.delays)
        if state.shape[-1] != self.n_carried + buffered:
            raise ValueError(
                f"this model's state holds {self.n_carried} observed and effect values and "
                f"{buffered} past controls, not {state.shape[-1]} values: start it from an "
                "observation with model.start(obs) or model.reset(key)"
            )
        if not self.delays:
            return self.predict(state, u)
        applied, buffer = self.delayed(state[self.n_carried :], u)
        return jnp.concatenate([self.predict(state[: self.n_carried], applied), buffer])

    def observe(self, state, params=None):
        return state[: self.n_obs] if state.shape[-1] > self.n_obs else state

    def qqd(self, state):
        return state[: self.nq], state[self.nq : self.n_obs]


def make_net(kind: str, hidden: Sequence[int], n_obs: int) -> MLP:
    return MLP(tuple(int(w) for w in hidden), n_obs, zero_last=kind == "residual")


def n_inputs(angular: np.ndarray, n_obs: int, n_act: int) -> int:
    return n_obs + int(np.sum(angular)) + n_act


def init_params(net: MLP, key, n_in: int, members: int):
    """Member-stacked initial parameters, each member from its own key."""
    return jax.vmap(lambda k: net.init(k, jnp.zeros(n_in)))(jax.random.split(key, members))


def skeleton(
    kind: str, env, hidden: Sequence[int], members: int, params=None, norm: Normalizer | None = None
) -> DynamicsModel:
    """A model for `env`'s system; parameters default to a fresh init (key 0), normalisation
    to the identity."""
    if kind not in KINDS:
        raise ValueError(f"unknown dynamics model '{kind}'; choose one of {list(KINDS)}")
    sim = env.sim
    base, base_params, delays, delay_params = (
        _base(env) if kind == "residual" else (None, None, EffectSet(), ())
    )
    net = make_net(kind, hidden, sim.n_obs)
    n_in = n_inputs(sim.angular, sim.n_obs, sim.n_act)
    if params is None:
        params = init_params(net, jax.random.PRNGKey(0), n_in, members)
    return DynamicsModel(
        kind=kind,
        net=net,
        params=params,
        norm=norm if norm is not None else Normalizer.identity(n_in, sim.n_obs),
        obs_names=tuple(sim.obs_names),
        action_names=tuple(sim.action_names),
        angular=np.asarray(sim.angular, dtype=bool),
        dt=float(sim.dt),
        ctrl_range=np.asarray(sim.ctrl_range, dtype=np.float32),
        task=env.task,
        sim=base,
        sim_params=base_params,
        delay_effects=delays,
        delay_params=delay_params,
    )


def _at_rest(sim):
    """(`sim`'s effect states at rest, raveled; the function that unravels such a vector)."""
    return ravel_pytree(sim.effects.init_state())


def _simulator_step(sim, nq: int, params, ctrl_range, obs, carried, u):
    """(the next [q, qd], the effect states after it) of `sim` from the observation `obs`
    with its effect states `carried` (raveled; None: at rest) under the control `u`, clipped
    to `ctrl_range`."""
    rest, unravel = _at_rest(sim)
    carried = rest if carried is None else carried
    state = sim.init(obs[:nq], obs[nq:], params)
    state = replace(state, effects=unravel(carried.astype(rest.dtype)))
    state = sim.step(params, state, jnp.clip(u, ctrl_range[:, 0], ctrl_range[:, 1]))
    return jnp.concatenate([state.q, state.qd]), ravel_pytree(state.effects)[0]


@partial(jax.jit, static_argnums=(0, 1))
def _effect_states_along(sim, nq: int, params, ctrl_range, obs, applied):
    """[T+1, n_effect_state] `sim`'s effect states along one recorded episode (obs [T+1,
    n_obs], applied [T, n_act]), from rest. Jitted on the simulator (hashable by identity,
    one per env: `_base`) and the shapes, its parameters traced."""
    rest = _at_rest(sim)[0]

    def step(carried, ou):
        return _simulator_step(sim, nq, params, ctrl_range, ou[0], carried, ou[1])[1], carried

    last, before = jax.lax.scan(step, rest, (obs[:-1], applied))
    return jnp.concatenate([before, last[None]])


_BASES: dict = {}


def _base(env):
    """(simulator, its effect parameters, action delays, theirs) of a residual model on
    `env`: env's simulator less its action delays (effects that shift actions, of one step or
    more), which the model applies itself, keeping their buffers in its state (a base step
    starts from rest). One per env, so the models fitted on it share what is compiled for
    its simulator (`_effect_states_along`)."""
    return _per_env(_BASES, env, (), lambda: _split_delays(env))


def _per_env(cache: dict, env, key: tuple, make):
    """`make()`, kept in `cache` per env object (and `key`): the env is held beside it, so an
    id reused by a later env is not mistaken for it."""
    full = (id(env), *key)
    if full not in cache or cache[full][0] is not env:
        cache[full] = (env, make())
    return cache[full][1]


def _split_delays(env):
    sim, params = env.sim, tuple(env.params)
    sites = sim.effects.sites
    shifts = [effect_type(s.name).shifts_actions for s in sites]
    if not any(shifts):
        return sim, params, EffectSet(), ()
    kept = [i for i, shifted in enumerate(shifts) if not shifted]
    delayed = [i for i, shifted in enumerate(shifts) if shifted and sites[i].static("steps") > 0]
    base = replace(sim, effects=EffectSet(tuple(sites[i] for i in kept)))
    delays = EffectSet(tuple(sites[i] for i in delayed))
    return base, tuple(params[i] for i in kept), delays, tuple(params[i] for i in delayed)


_ZERO: dict = {}


def zero_residual(env, hidden: Sequence[int] = (8,)) -> DynamicsModel:
    """A residual model whose correction is exactly zero: the simulator itself (one object per
    env and width, so what is compiled for it is reused)."""

    def make():
        model = skeleton("residual", env, hidden, 1)
        return replace(model, params=jax.tree.map(jnp.zeros_like, model.params))

    return _per_env(_ZERO, env, (tuple(hidden),), make)


@dataclass(frozen=True)
class ConstantVelocity:
    """The baseline step: q' = q + dt qd, qd' = qd (q held when nq != nv). Hashable by value."""

    dt: float
    nq: int

    def __call__(self, obs, u):
        q, qd = obs[: self.nq], obs[self.nq :]
        return jnp.concatenate([q + self.dt * qd if qd.shape == q.shape else q, qd])


def constant_velocity(dt: float, nq: int) -> ConstantVelocity:
    return ConstantVelocity(float(dt), int(nq))
