"""PODS and HDS: one trainer, made of parts.

`make_train(env=..., policy=..., improvement=..., ...)` builds a `Trainer` of pure functions
from its parts, in the style of PureJaxRL and brax's agents; `make_train_from_config(cfg, env)`
builds the parts from a validated config (docs/trainer.md). The trainer's functions:
  init(key, hparams) -> TrainState
  run_chunk(state, hparams) -> (state, metrics)   `chunk` epochs as one lax.scan
  train(key, hparams) -> (state, metrics)         the whole run as one program
`hparams` holds the numeric hyperparameters (step size, noise scale, effect parameters of the
simulator), so `jax.jit(jax.vmap(train))` trains many seeds or settings in one compiled program
(hds.run maps them as `vmap_runs` says: vmapped on a GPU, in a `lax.map` loop on one CPU).

One epoch:
  1. roll the policy out (plus exploration noise) from a batch of initial states; a static
     share `beta` of the batch runs through a learned dynamics model instead of the
     simulator (two batches of fixed size: no per-sample switch, which would run both), as
     short rollouts from states the simulator's visited where `ModelShare.branch` says so;
  2. improve every action sequence with the gradient of its return (hds/algo/improve.py);
  3. regress the policy onto the improved actions (hds/algo/regress.py).
The continuation (hds/algo/continuation.py) says where the effects' ramp and the horizon
curriculum stand at each epoch, and keeps what it tracks in `TrainState.progress`.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from hds import anneal, noise
from hds.algo.continuation import Continuation, Progress, ramp_effects
from hds.algo.improve import ImproveSettings, improve
from hds.algo.randomize import Randomization
from hds.algo.regress import regress
from hds.algo.rollout import perturbed_rollout, policy_rollout
from hds.networks import make_policy
from hds.utils.pytree import pytree_dataclass


@pytree_dataclass
class TrainState:
    policy: dict
    opt_state: optax.OptState
    epoch: jax.Array
    key: jax.Array
    progress: Progress  # the continuation's: one structure for every configuration


# --- the parts ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Budget:
    epochs: int
    rollouts: int  # per epoch, the simulator's and the model's together
    chunk: int = 1  # at most this many epochs per compiled chunk (a divisor of epochs)


@dataclass(frozen=True)
class Improvement:
    """Stage 2: how every rollout's actions are improved (hds/algo/improve.py)."""

    settings: ImproveSettings
    step_size: float  # the base step alpha (hparams["step_size"], may be swept)
    step_decay: float = 1.0  # alpha <- alpha * step_decay per epoch
    temperature: float = 1.0  # simulated annealing's initial temperature ...
    cooling: float = 0.9  # ... times cooling per epoch
    steps: int = 1  # improvement steps per epoch, each from the last one's actions
    closed_loop: bool = False  # improve perturbations of the policy's controls, not the controls


@dataclass(frozen=True)
class Regression:
    """Stage 3: regress the policy onto the improved actions (hds/algo/regress.py)."""

    optimizer: optax.GradientTransformation
    inner_epochs: int
    minibatch: int
    early_stop: float  # the relative loss change that stops the inner epochs (-inf: never)


@dataclass(frozen=True)
class Exploration:
    """The noise on the policy's actions while collecting: `schedule(scale, decay)` is
    epoch -> standard deviation (hds/noise.py); scale and decay may be traced (swept)."""

    schedule: Callable
    scale: float
    decay: float = 1.0


@dataclass(frozen=True)
class ModelShare:
    """How many of the rollouts run through a learned model (HDS)."""

    beta: float = 0.0  # the share (hparams["beta"], may be swept)
    betas: tuple[float, ...] = ()  # every share a batch of runs sweeps; (): (beta,)
    branch: int = 0  # n: each model rollout becomes short ones of n steps (0: whole ones)


# --- what the stages return --------------------------------------------------------------------


class Collected(NamedTuple):  # stage 1
    starts: object  # the initial states
    obs: jax.Array  # [B, T, n_obs]
    actions: jax.Array  # [B, T, n_act]
    rewards: jax.Array  # [B, T]
    key: jax.Array  # left for stage 2


class Targets(NamedTuple):  # stage 2
    obs: jax.Array  # the regression's inputs: the rollouts' (closed loop: the improved ones')
    result: object  # improve.Improved; its actions are the regression targets
    alpha: jax.Array  # the step size


class BatchOutcome(NamedTuple):  # stages 1 and 2 of one batch of rollouts
    targets: Targets
    returns: jax.Array  # [B] each rollout's return
    visited: jax.Array  # [B, T, n_obs] the observations the rollouts visited
    commanded: jax.Array  # [B, T, n_act] the controls they commanded there


@dataclass(frozen=True)
class Stages:
    """An epoch's three stages on the simulator, the functions the epoch itself runs (so
    benchmarks time the real ones); jit them yourself. `params`: the effect parameters.
      collect(params, count, policy_params, hparams, epoch, key) -> Collected
      improve(params, policy_params, hparams, epoch, starts, obs, actions, key) -> Targets
      regress(policy_params, opt_state, obs [N, n_obs], targets [N, n_act], key, tol=...)
          -> (policy_params, opt_state, loss)"""

    collect: Callable
    improve: Callable
    regress: Callable


@dataclass(frozen=True)
class Trainer:
    init: Callable
    run_chunk: Callable
    train: Callable
    final_policy: Callable  # state -> the policy the run returns (keep-best); batched or not
    chunk: int  # epochs per chunk
    policy: object  # init/apply as a flax module's (hds.networks.Policy); params: TrainState.policy
    default_hparams: dict
    stages: Stages


def chunk_length(epochs: int, most: int) -> int:
    """The largest divisor of `epochs` not above `most`: every chunk then has one shape."""
    return max(d for d in range(1, min(epochs, most) + 1) if epochs % d == 0)


def branch_starts(visited, n_used, count: int, key, commanded=None, history: int = 0):
    """`count` initial observations for branched model rollouts, each drawn uniformly from
    the states the first `n_used` (may be traced) of the rollouts `visited` ([n, T, n_obs])
    reached. One key per draw, so a batch with more draws begins with the same ones (a beta
    sweep). With `history` > 0, also the `history` controls `commanded` ([n, T, n_act]) before
    each, oldest first (zeros before the rollout's start): a model's delay buffers."""

    def draw(k):
        k_which, k_when = jax.random.split(k)
        which = jnp.floor(jax.random.uniform(k_which) * n_used).astype(jnp.int32)
        when = jax.random.randint(k_when, (), 0, visited.shape[1])
        if not history:
            return visited[which, when]
        before = jnp.pad(commanded[which], ((history, 0), (0, 0)))
        return visited[which, when], jax.lax.dynamic_slice_in_dim(before, when, history)

    return jax.vmap(draw)(jax.random.split(key, count))


# --- the trainer -------------------------------------------------------------------------------


def make_train(
    *,
    env,
    policy,
    improvement: Improvement,
    regression: Regression,
    continuation: Continuation,
    exploration: Exploration,
    budget: Budget,
    model=None,
    model_share: ModelShare | None = None,
    randomize: Randomization | None = None,
) -> Trainer:
    """The trainer of `policy` (a flax module of the observation) on `env`, from its parts;
    `model`: an optional learned dynamics engine (reset/step/observe/qqd) through which
    `model_share` of the rollouts runs; `randomize`: domain randomization, each simulator
    rollout with its own draw of the effect parameters."""
    model_share = model_share or ModelShare()
    split = Split.of(budget, env.task.horizon, model, model_share, continuation.ramped)
    stages = _Stages(env, policy, improvement, regression, exploration, continuation, split)

    def init(key, hparams) -> TrainState:
        key, init_key = jax.random.split(key)
        params = policy.init(init_key, jnp.zeros(env.sim.n_obs))
        opt_state, progress = regression.optimizer.init(params), continuation.init(params)
        return TrainState(params, opt_state, jnp.array(0, jnp.int32), key, progress)

    def on_simulator(state, hparams, share, key) -> BatchOutcome:
        params = hparams["effects"]
        if randomize is not None:  # the key folded in: a range of no width trains as its value
            params = randomize.draw(jax.random.fold_in(key, 1), hparams, split.n_sim)
        if continuation.ramped:
            params = ramp_effects(params, env.sim.effects.sites, share)
        return stages.batch(env, params, split.n_sim, state, hparams, key, randomize is not None)

    def on_model(state, hparams, sim: BatchOutcome, n_used, key) -> BatchOutcome:
        starts = None  # whole rollouts from the task's initial states, or branches:
        if split.branched:
            history = getattr(model, "history", 0)  # a model with delays: their buffers too
            drawn = branch_starts(
                sim.visited,
                n_used,
                split.n_model,
                jax.random.fold_in(key, 1),
                sim.commanded,
                history,
            )
            # the model's state there: its delays' buffers hold what was commanded before,
            # its effect states (a lag's filter) start at rest
            starts = jax.vmap(model.start)(*drawn) if history else jax.vmap(model.start)(drawn)
        return stages.batch(model, None, split.n_model, state, hparams, key, False, starts)

    def epoch(state: TrainState, hparams):
        # the same keys whether or not a model takes part: a run with beta = 0 in a beta sweep
        # is the run without a model
        key, sim_key, regress_key, model_key = jax.random.split(state.key, 4)
        point = continuation.at(state.progress, state.epoch)
        used = split.used(hparams["beta"] * point.share)
        outs = [on_simulator(state, hparams, point.share, sim_key)]
        if split.n_model:
            outs.append(on_model(state, hparams, outs[0], used.n_sim, model_key))
        obs, targets, weights = split.regression_rows(outs, used, point.counted)
        params, opt_state, loss = stages.regress(
            state.policy, state.opt_state, obs, targets, regress_key, weights=weights
        )
        metrics = _metrics(outs, used, loss, stages.sigma(hparams, state.epoch))
        if continuation.ramped:  # how far the continuation has gone: 0 before it, 1 at its end
            metrics["ramp"] = point.share
        progress = continuation.update(
            state.progress, state.epoch, point, state.policy, metrics["return"]
        )
        return TrainState(params, opt_state, state.epoch + 1, key, progress), metrics

    chunk = chunk_length(budget.epochs, budget.chunk)

    def run_chunk(state, hparams):
        return jax.lax.scan(lambda s, _: epoch(s, hparams), state, None, length=chunk)

    def train(key, hparams):
        state = init(key, hparams)
        return jax.lax.scan(lambda s, _: epoch(s, hparams), state, None, length=budget.epochs)

    def final_policy(state):
        return continuation.final_policy(state.progress, state.policy)

    hparams = {
        "step_size": jnp.asarray(improvement.step_size, jnp.float32),
        "noise_scale": jnp.asarray(exploration.scale, jnp.float32),
        "noise_decay": jnp.asarray(exploration.decay, jnp.float32),
        "beta": jnp.asarray(model_share.beta, jnp.float32),
        "effects": env.params,
        **(randomize.hparams() if randomize is not None else {}),
    }
    return Trainer(init, run_chunk, train, final_policy, chunk, policy, hparams, stages.public())


def _metrics(outs: list[BatchOutcome], used: Used, loss, sigma) -> dict:
    """An epoch's metrics over the rollouts this run uses (the static batches hold those of
    the widest run of a sweep)."""

    def of(value_of, part):  # a batch's values, NaN where this run does not use them
        return jnp.where(used.masks[part], value_of(outs[part]), jnp.nan)

    def of_all(value_of):
        return jnp.concatenate([of(value_of, p) for p in range(len(outs))])

    return {
        "return": jnp.nanmean(of(lambda o: o.returns, 0)),  # the noisy policy's, on the simulator
        "improved_return": jnp.nanmean(of(lambda o: o.targets.result.new_value, 0)),
        "loss": loss,
        "step_size": outs[0].targets.alpha,
        "noise": sigma,
        "accepted": jnp.nanmean(of_all(lambda o: o.targets.result.accepted)),
        "skipped": jnp.nansum(of_all(lambda o: o.targets.result.skipped)),
    }


# --- the split of an epoch's rollouts ----------------------------------------------------------


class Used(NamedTuple):
    """The rollouts one run uses of the static batches, at its model share."""

    n_sim: jax.Array  # of the simulator batch, its first n_sim
    masks: list  # per batch, [count] bool
    rows: jax.Array  # the regression's rows of the batches' flattened steps, the simulator's first


@dataclass(frozen=True)
class Split:
    """An epoch's rollouts as two batches of static size, the simulator's and the model's. A
    swept beta (a batch of runs) runs the widest split, and each run uses its own share of it
    (`used`), so every run sees the rollouts a run with that beta alone would
    (jax.random.split's keys are prefix-consistent). The model's share grows in with the
    effects (the continuation's ramp): from none while the policy learns on the simulator
    alone, as dry friction does, whose gradient a model of the plant carries too."""

    rollouts: int
    horizon: int
    n_sim: int  # the simulator batch: the rollouts of the narrowest model share
    n_model: int  # the model batch: the rollouts of the widest share, times per_slot
    per_slot: int  # short rollouts per model rollout (branches)
    branch: int  # a model rollout's steps
    branched: bool

    @classmethod
    def of(cls, budget: Budget, horizon: int, model, share: ModelShare, ramped: bool) -> Split:
        betas = (share.betas or (share.beta,)) if model is not None else (0.0,)
        if ramped:
            betas = (*betas, 0.0)
        # the build's counts in numpy: the same float32 rounding, without an eager jax op each
        # (~15 ms of a second process: a trace, a lowering and a compilation-cache read)
        widest = int(_model_count(max(betas), budget.rollouts, np))
        narrowest = int(_model_count(min(betas), budget.rollouts, np))
        # each model rollout becomes horizon / branch short ones, each started from a state
        # the simulator's rollouts visited (MBPO's branched rollouts), so a model's error
        # compounds over `branch` steps, not the whole horizon; the same rows to regress
        branched = bool(share.branch) and bool(widest)
        branch = chunk_length(horizon, share.branch) if branched else horizon
        per_slot = horizon // branch
        n_sim = budget.rollouts - narrowest
        return cls(budget.rollouts, horizon, n_sim, widest * per_slot, per_slot, branch, branched)

    def used(self, beta) -> Used:
        n_model = _model_count(beta, self.rollouts) if self.n_model else 0
        n_sim = self.rollouts - n_model
        i = jnp.arange(self.rollouts * self.horizon)
        rows = jnp.where(i < n_sim * self.horizon, i, (self.n_sim - n_sim) * self.horizon + i)
        counts = (self.n_sim, self.n_model) if self.n_model else (self.n_sim,)
        masks = [jnp.arange(n) < k for n, k in zip(counts, (n_sim, n_model * self.per_slot))]
        return Used(n_sim, masks, rows)

    def regression_rows(self, outs: list[BatchOutcome], used: Used, counted):
        """(obs, targets, weights) of the rows this run regresses on; the steps the horizon
        curriculum did not count were not improved: weight 0 (a branch's steps all count)."""
        n_obs, n_act = outs[0].visited.shape[-1], outs[0].targets.result.actions.shape[-1]
        obs = jnp.concatenate([o.targets.obs.reshape(-1, n_obs) for o in outs])[used.rows]
        actions = [o.targets.result.actions.reshape(-1, n_act) for o in outs]
        targets = jnp.concatenate(actions)[used.rows]
        if counted is None:
            return obs, targets, None
        step = jnp.arange(self.rollouts * self.horizon)
        weights = counted[step % self.horizon]
        if self.branched:
            weights = jnp.where(step < used.n_sim * self.horizon, weights, 1.0)
        return obs, targets, weights


def _model_count(beta, rollouts: int, xp=jnp):
    """The rollouts of a batch that run on the model at share `beta` (`xp`: jax.numpy where
    `beta` is traced, numpy for a number)."""
    return xp.round(xp.float32(beta) * rollouts).astype(xp.int32)


# --- the stages --------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Stages:
    """The three stages of an epoch, on any engine (the simulator or a learned model)."""

    env: object
    policy: object
    improvement: Improvement
    regression: Regression
    exploration: Exploration
    continuation: Continuation
    split: Split

    @property
    def bounds(self):
        ctrl = self.env.sim.ctrl_range
        return jnp.asarray(ctrl[:, 0]), jnp.asarray(ctrl[:, 1])

    def public(self) -> Stages:
        return Stages(
            functools.partial(self.collect, self.env),
            functools.partial(self.improve, self.env),
            self.regress,
        )

    def sigma(self, hparams, epoch):
        return self.exploration.schedule(hparams["noise_scale"], hparams["noise_decay"])(epoch)

    def batch(self, engine, params, count, state, hparams, key, drawn, starts=None):
        """Stages 1 and 2 of `count` rollouts on `engine`."""
        episodes = starts is None  # given starts: branches, mid-episode
        got = self.collect(
            engine, params, count, state.policy, hparams, state.epoch, key, drawn, starts
        )
        targets = self.improve(
            engine,
            params,
            state.policy,
            hparams,
            state.epoch,
            got.starts,
            got.obs,
            got.actions,
            got.key,
            drawn,
            episodes,
        )
        return BatchOutcome(targets, got.rewards.sum(-1), got.obs, got.actions)

    def collect(
        self,
        engine,
        params,
        count,
        policy_params,
        hparams,
        epoch,
        key,
        per_rollout=False,
        starts=None,
    ) -> Collected:
        """Stage 1: roll the (noisy) policy out from `count` initial states (`per_rollout`:
        params holds each rollout's own effect parameters, batched on axis 0; `starts`: given
        ones, rolled out for a branch's steps, not drawn ones for the horizon)."""
        k_reset, k_roll, k_improve = jax.random.split(key, 3)
        steps = self.env.task.horizon if starts is None else self.split.branch
        if starts is None:
            starts = jax.vmap(engine.reset)(jax.random.split(k_reset, count))
        act = lambda o: self.policy.apply(policy_params, o)  # noqa: E731
        sigma, (low, high) = self.sigma(hparams, epoch), self.bounds
        obs, actions, rewards = jax.vmap(
            lambda p, s, k: policy_rollout(
                engine, p, self.env.task, act, s, k, sigma, steps, low, high
            ),
            in_axes=(0 if per_rollout else None, 0, 0),
        )(params, starts, jax.random.split(k_roll, count))
        return Collected(starts, obs, actions, rewards, k_improve)

    def improve(
        self,
        engine,
        params,
        policy_params,
        hparams,
        epoch,
        starts,
        obs,
        actions,
        key,
        per_rollout=False,
        episodes=True,
    ) -> Targets:
        """Stage 2: improve every rollout's actions (open loop) or perturbations of the
        policy's controls (closed loop); the result's actions are the regression targets, and
        (closed loop) its observations the improved trajectory's. `episodes`: the rollouts
        start where episodes do (the horizon curriculum counts their first steps), not
        mid-episode (branches)."""
        part, (low, high) = self.improvement, self.bounds
        count = jax.tree.leaves(starts)[0].shape[0]
        p_axis = 0 if per_rollout else None
        act = lambda o: self.policy.apply(policy_params, o)  # noqa: E731
        alpha = anneal.step_size(hparams["step_size"], part.step_decay, epoch)
        temp = anneal.temperature(part.temperature, part.cooling, epoch)
        counted = self.continuation.counted(epoch) if episodes else None
        step = jax.vmap(
            lambda p, s, a, k: improve(
                engine,
                p,
                self.env.task,
                s,
                a,
                k,
                alpha=alpha,
                temperature=temp,
                cfg=part.settings,
                low=low,
                high=high,
                act=act if part.closed_loop else None,
                counted=counted,
            ),
            in_axes=(p_axis, 0, 0, 0),
        )
        if part.closed_loop:  # the perturbations that reproduce the rollout: u = act(o) + delta
            actions = actions - jax.vmap(jax.vmap(act))(obs)
        result = step(params, starts, actions, jax.random.split(key, count))
        if part.steps > 1:  # further steps from the improved actions

            def again(result, k):
                nxt = step(params, starts, result.actions, jax.random.split(k, count))
                return nxt._replace(
                    value=result.value,
                    accepted=result.accepted | nxt.accepted,
                    skipped=result.skipped | nxt.skipped,
                ), None

            keys = jax.random.split(jax.random.fold_in(key, 1), part.steps - 1)
            result, _ = jax.lax.scan(again, result, keys)
        if part.closed_loop:  # regress onto the improved trajectory: its states and controls
            obs, controls, _ = jax.vmap(
                lambda p, s, d: perturbed_rollout(engine, p, self.env.task, act, s, d, low, high),
                in_axes=(p_axis, 0, 0),
            )(params, starts, result.actions)
            result = result._replace(actions=controls)
        return Targets(obs, result, alpha)

    def regress(self, params, opt_state, obs, targets, key, tol=None, weights=None):
        """Stage 3: regress the policy onto the targets (rows of obs [N, n_obs] and targets
        [N, n_act], `weights` [N], default 1); `tol`: the early stop (default the part's;
        -inf: every inner epoch)."""
        part = self.regression
        return regress(
            self.policy.apply,
            part.optimizer,
            params,
            opt_state,
            obs,
            targets,
            jnp.ones(obs.shape[0]) if weights is None else weights,
            key,
            inner_epochs=part.inner_epochs,
            minibatch=part.minibatch,
            tol=part.early_stop if tol is None else tol,
        )


# --- from a config -----------------------------------------------------------------------------


def make_train_from_config(cfg, env, model=None, randomization=None) -> Trainer:
    """The trainer a validated `hds.config.Config` describes, on `env`; `model`: an optional
    learned dynamics engine through which a share `cfg.dynamics.beta` of rollouts runs;
    `randomization`: domain randomization (hds.algo.randomize.randomization), which the
    simulator kind hands in (hds.simulators), as brax's `randomization_fn`."""
    algo, anneal_cfg, task = cfg.algo, cfg.anneal, env.task
    epochs = algo.epochs
    solved_at = cfg.env.task.solved_at if anneal_cfg.ramp_when_solved else None
    continuation = Continuation(
        epochs=epochs,
        ramp=tuple(share * epochs for share in anneal_cfg.effect_ramp),
        solved_at=solved_at,
        solved_for=anneal_cfg.solved_for,
        pauses=anneal_cfg.ramp_pauses,
        keep_best=algo.keep == "best",
        horizon=task.horizon,
        horizon_start=anneal_cfg.horizon_start,
        horizon_full_at=anneal_cfg.horizon_full_at * epochs,
    )
    settings = ImproveSettings(
        algo.order,
        algo.grad_clip,
        algo.gn_damping,
        anneal.candidates(anneal_cfg.kind, algo.line_search),
        anneal_cfg.kind,
        algo.grad_window,
    )
    improvement = Improvement(
        settings,
        algo.step_size,
        anneal_cfg.step_decay,
        anneal_cfg.temperature,
        anneal_cfg.cooling,
        algo.improve_steps,
        algo.improve_in == "closed_loop",
    )
    regression = Regression(
        optax.adam(algo.learning_rate), algo.inner_epochs, algo.minibatch, algo.early_stop
    )
    exploration = Exploration(
        functools.partial(noise.schedule, cfg.noise, epochs), cfg.noise.scale, cfg.noise.decay
    )
    betas = tuple(cfg.sweep.beta or ())
    return make_train(
        env=env,
        policy=make_policy(algo.hidden, env.sim),
        improvement=improvement,
        regression=regression,
        continuation=continuation,
        exploration=exploration,
        budget=Budget(epochs, algo.rollouts, algo.chunk),
        model=model,
        model_share=ModelShare(cfg.dynamics.beta, betas, cfg.dynamics.branch),
        randomize=randomization,
    )
