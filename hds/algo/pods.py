"""PODS and HDS: one trainer, two configurations.

`make_train(cfg, env)` returns a `Trainer` of pure functions, in the style of PureJaxRL:
  init(key, hparams) -> TrainState
  run_chunk(state, hparams) -> (state, metrics)   `chunk` epochs as one lax.scan
  train(key, hparams) -> (state, metrics)         the whole run as one program
`hparams` holds the numeric hyperparameters (step size, noise scale, effect parameters of the
simulator), so `jax.jit(jax.vmap(train))` trains many seeds or settings in one compiled program
(hds.run maps them as `vmap_runs` says: vmapped on a GPU, in a `lax.map` loop on one CPU).

One epoch:
  1. roll the policy out (plus exploration noise) from a batch of initial states; a static
     share `dynamics.beta` of the batch runs through a learned dynamics model instead of the
     simulator (two batches of fixed size: no per-sample switch, which would run both), as
     short rollouts from states the simulator's visited where `dynamics.branch` says so;
  2. improve every action sequence with the gradient of its return (hds/algo/improve.py);
  3. regress the policy onto the improved actions (hds/algo/regress.py).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import optax
from flax import struct

from hds import anneal, noise
from hds.algo.improve import ImproveSettings, improve
from hds.algo.regress import regress
from hds.algo.rollout import perturbed_rollout, policy_rollout
from hds.networks import make_policy


@struct.dataclass
class TrainState:
    policy: dict
    opt_state: optax.OptState
    epoch: jax.Array
    key: jax.Array
    # what the configuration tracks across epochs: "solved", the epoch the policy had solved
    # the task anneal.solved_for epochs in a row, "streak", how many it has now (only when
    # more than one; anneal.ramp_when_solved), "paused", the epochs the ramp stood still
    # (anneal.ramp_pauses); "best" and "best_return", the kept policy (algo.keep)
    progress: dict = struct.field(default_factory=dict)


@dataclass(frozen=True)
class Stages:
    """An epoch's three stages on the simulator, the functions the epoch itself runs (so
    benchmarks time the real ones); jit them yourself. `params`: the effect parameters.
      collect(params, count, policy_params, hparams, epoch, key)
          -> (starts, obs [B, T, n_obs], actions [B, T, n_act], rewards [B, T], improve_key)
      improve(params, policy_params, hparams, epoch, starts, obs, actions, key)
          -> (obs, ImproveResult whose actions are the regression targets, alpha)
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
    final_policy: Callable  # state -> the policy the run returns (algo.keep); batched or not
    chunk: int  # epochs per chunk
    policy: object  # the flax module; apply with TrainState.policy
    default_hparams: dict
    stages: Stages


def chunk_length(epochs: int, most: int) -> int:
    """The largest divisor of `epochs` not above `most`: every chunk then has one shape."""
    return max(d for d in range(1, min(epochs, most) + 1) if epochs % d == 0)


def branch_starts(visited, n_used, count: int, key):
    """`count` initial states for branched model rollouts, each drawn uniformly from the
    states the first `n_used` (may be traced) of the rollouts `visited` ([n, T, n_obs]; a
    model's state is its observation) reached. One key per draw, so a batch with more draws
    begins with the same ones (a beta sweep)."""

    def draw(k):
        k_which, k_when = jax.random.split(k)
        which = jnp.floor(jax.random.uniform(k_which) * n_used).astype(jnp.int32)
        return visited[which, jax.random.randint(k_when, (), 0, visited.shape[1])]

    return jax.vmap(draw)(jax.random.split(key, count))


def make_train(cfg, env, model=None, randomization=None) -> Trainer:
    """`cfg` is a validated `hds.config.Config`; `model` an optional learned dynamics engine
    (reset/step/observe/qqd) through which a share `cfg.dynamics.beta` of rollouts runs;
    `randomization` (hds.algo.randomize.Randomization, as brax's randomization_fn) draws each
    simulator rollout's effect parameters (None: every rollout on the run's own)."""
    algo, task, sim = cfg.algo, env.task, env.sim
    low, high = jnp.asarray(sim.ctrl_range[:, 0]), jnp.asarray(sim.ctrl_range[:, 1])
    policy = make_policy(algo.hidden, sim)
    optimizer = optax.adam(algo.learning_rate)

    def sigma(hp, epoch):
        return noise.schedule(cfg.noise, algo.epochs, hp["noise_scale"], hp["noise_decay"])(epoch)

    settings = ImproveSettings(
        algo.order,
        algo.grad_clip,
        algo.gn_damping,
        anneal.candidates(cfg.anneal.kind, algo.line_search),
        cfg.anneal.kind,
        algo.grad_window,
    )

    ramp = [share * algo.epochs for share in cfg.anneal.effect_ramp]  # [begin, end] epochs

    def counted_steps(epoch):  # anneal.horizon_start's curriculum; None: the whole horizon
        full_at = cfg.anneal.horizon_full_at * algo.epochs
        return anneal.counted_steps(epoch, cfg.anneal.horizon_start, full_at, task.horizon)

    solved_at = cfg.env.task.solved_at
    gated = bool(ramp[1]) and cfg.anneal.ramp_when_solved and solved_at is not None
    solved_for = cfg.anneal.solved_for
    pauses = gated and cfg.anneal.ramp_pauses
    keep_best = algo.keep == "best"

    def ramp_delay(state):
        """Epochs the ramp waits for the policy to solve the task: until the epoch after it
        first did so `anneal.solved_for` epochs in a row, plus (anneal.ramp_pauses) each
        epoch on the ramp it failed, at most until the ramp ends on the last epoch."""
        if not gated:
            return 0
        waited = state.progress["solved"] + 1 - ramp[0] + state.progress.get("paused", 0)
        return jnp.clip(waited, 0, algo.epochs - ramp[1])

    # The split of the batch is static: a swept beta (sweep.beta) runs the widest split, and
    # each run uses its own share of it (`shares`), so every run sees the rollouts a run with
    # that beta alone would (jax.random.split's keys are prefix-consistent). The model's share
    # grows in with the effects (anneal.effect_ramp): from none while the policy learns on the
    # simulator alone, as dry friction does, whose gradient a model of the plant carries too.
    def model_count(beta):
        return jnp.round(jnp.float32(beta) * algo.rollouts).astype(jnp.int32)

    betas = (cfg.sweep.beta or [cfg.dynamics.beta]) if model is not None else [0.0]
    if ramp[1]:
        betas = [*betas, 0.0]
    n_model_max, n_model_min = int(model_count(max(betas))), int(model_count(min(betas)))
    # dynamics.branch: each of the model's rollouts becomes horizon / branch short ones, each
    # started from a state the simulator's rollouts visited (MBPO's branched rollouts), so a
    # model's error compounds over `branch` steps, not the whole horizon; same rows to regress
    horizon = task.horizon
    branched = bool(cfg.dynamics.branch) and bool(n_model_max)
    branch = chunk_length(horizon, cfg.dynamics.branch) if branched else horizon
    per_slot = horizon // branch
    parts = [(env, algo.rollouts - n_model_min, "effects")]
    if n_model_max:
        parts.append((model, n_model_max * per_slot, None))

    def shares(hparams, ramp_share):
        """Where the continuation stands at `ramp_share`: how many of the simulator part's
        rollouts this run uses, per part which of its rollouts it uses, and the regression's
        rows (the used steps of the parts' flattened rollouts, the simulator's first)."""
        beta = hparams["beta"] * ramp_share
        n_model = model_count(beta) if n_model_max else 0
        n_sim = algo.rollouts - n_model
        i = jnp.arange(algo.rollouts * horizon)
        rows = jnp.where(i < n_sim * horizon, i, (parts[0][1] - n_sim) * horizon + i)
        masks = [jnp.arange(n) < k for (_, n, _), k in zip(parts, (n_sim, n_model * per_slot))]
        return n_sim, masks, rows

    def init(key, hparams) -> TrainState:
        key, init_key = jax.random.split(key)
        params = policy.init(init_key, jnp.zeros(sim.n_obs))
        progress = {}
        if gated:
            progress["solved"] = jnp.array(algo.epochs, jnp.int32)  # not yet
            if solved_for > 1:  # one epoch (the default) needs no count: checkpoints as before
                progress["streak"] = jnp.array(0, jnp.int32)  # epochs in a row at solved_at
            if pauses:
                progress["paused"] = jnp.array(0, jnp.int32)  # failed epochs on the ramp
        if keep_best:
            progress |= {"best": params, "best_return": jnp.float32(-jnp.inf)}
        return TrainState(params, optimizer.init(params), jnp.array(0, jnp.int32), key, progress)

    def track(state, sim_return, ramp_share):
        """The next epoch's `progress`, after the policy's return on the simulator at the
        continuation's `ramp_share`."""
        progress = dict(state.progress)
        if gated:
            solved_now = sim_return >= solved_at
            streak = jnp.where(solved_now, state.progress.get("streak", 0) + 1, 0)
            first = (state.progress["solved"] == algo.epochs) & (streak >= solved_for)
            if solved_for > 1:
                progress["streak"] = streak
            progress["solved"] = jnp.where(first, state.epoch, state.progress["solved"])
            if pauses:
                failed = (ramp_share > 0) & (ramp_share < 1) & ~solved_now
                progress["paused"] = state.progress["paused"] + failed.astype(jnp.int32)
        if keep_best:  # among the epochs with the continuation at its end
            better = (ramp_share >= 1) & (sim_return > state.progress["best_return"])
            progress["best_return"] = jnp.where(better, sim_return, state.progress["best_return"])
            progress["best"] = jax.tree.map(
                lambda kept, now: jnp.where(better, now, kept), state.progress["best"], state.policy
            )
        return progress

    def final_policy(state):
        if not keep_best:
            return state.policy
        found = state.progress["best_return"] > -jnp.inf  # [] or one per run of a batch

        def pick(kept, last):
            where = found.reshape(found.shape + (1,) * (kept.ndim - found.ndim))
            return jnp.where(where, kept, last)

        return jax.tree.map(pick, state.progress["best"], state.policy)

    randomized = randomization is not None

    def collect(
        engine, params, count, policy_params, hparams, epoch, key, per_rollout=False, starts=None
    ):
        """Stage 1: roll the (noisy) policy out from `count` initial states (`per_rollout`:
        params holds each rollout's own effect parameters, batched on axis 0; `starts`: given
        ones, rolled out for `branch` steps, not drawn ones for the horizon). Returns the
        starts, observations, controls, rewards and the key left for stage 2."""
        k_reset, k_roll, k_improve = jax.random.split(key, 3)
        steps = horizon if starts is None else branch
        if starts is None:
            starts = jax.vmap(engine.reset)(jax.random.split(k_reset, count))
        act = lambda o: policy.apply(policy_params, o)  # noqa: E731
        obs, actions, rewards = jax.vmap(
            lambda p, s, k: policy_rollout(
                engine, p, task, act, s, k, sigma(hparams, epoch), steps, low, high
            ),
            in_axes=(0 if per_rollout else None, 0, 0),
        )(params, starts, jax.random.split(k_roll, count))
        return starts, obs, actions, rewards, k_improve

    def improve_batch(
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
    ):
        """Stage 2: improve every rollout's actions (open loop) or perturbations of the
        policy's controls (closed loop); the result's actions are the regression targets, and
        (closed loop) its observations the improved trajectory's. `episodes`: the rollouts
        start where episodes do (the horizon curriculum counts their first steps), not
        mid-episode (branches). Returns (obs, result, alpha)."""
        count = jax.tree.leaves(starts)[0].shape[0]
        p_axis = 0 if per_rollout else None
        act = lambda o: policy.apply(policy_params, o)  # noqa: E731
        alpha = anneal.step_size(hparams["step_size"], cfg.anneal.step_decay, epoch)
        temp = anneal.temperature(cfg.anneal.temperature, cfg.anneal.cooling, epoch)
        closed = algo.improve_in == "closed_loop"
        step = jax.vmap(
            lambda p, s, a, k: improve(
                engine,
                p,
                task,
                s,
                a,
                k,
                alpha=alpha,
                temperature=temp,
                cfg=settings,
                low=low,
                high=high,
                act=act if closed else None,
                counted=counted_steps(epoch) if episodes else None,
            ),
            in_axes=(p_axis, 0, 0, 0),
        )
        if closed:  # the perturbations that reproduce the rollout: u = act(o) + delta
            actions = actions - jax.vmap(jax.vmap(act))(obs)
        result = step(params, starts, actions, jax.random.split(key, count))
        if algo.improve_steps > 1:  # further steps from the improved actions

            def again(result, k):
                nxt = step(params, starts, result.actions, jax.random.split(k, count))
                return nxt._replace(
                    value=result.value,
                    accepted=result.accepted | nxt.accepted,
                    skipped=result.skipped | nxt.skipped,
                ), None

            keys = jax.random.split(jax.random.fold_in(key, 1), algo.improve_steps - 1)
            result, _ = jax.lax.scan(again, result, keys)
        if closed:  # regress onto the improved trajectory: its states and its controls
            obs, controls, _ = jax.vmap(
                lambda p, s, d: perturbed_rollout(engine, p, task, act, s, d, low, high),
                in_axes=(p_axis, 0, 0),
            )(params, starts, result.actions)
            result = result._replace(actions=controls)
        return obs, result, alpha

    def regress_batch(params, opt_state, obs, targets, key, tol=algo.early_stop, weights=None):
        """Stage 3: regress the policy onto the targets (rows of obs [N, n_obs] and targets
        [N, n_act], `weights` [N], default 1); `tol`: the early stop (-inf: every inner epoch)."""
        return regress(
            policy.apply,
            optimizer,
            params,
            opt_state,
            obs,
            targets,
            jnp.ones(obs.shape[0]) if weights is None else weights,
            key,
            inner_epochs=algo.inner_epochs,
            minibatch=algo.minibatch,
            tol=tol,
        )

    def collect_and_improve(engine, params_key, count, state, hparams, key, delay, starts=None):
        params = hparams[params_key] if params_key else None
        # domain randomization: each rollout its own draw (params batched on axis 0); the key
        # is folded in, so a range of no width trains exactly as that value alone
        drawn = randomized and params_key == "effects"
        if drawn:
            params = randomization(jax.random.fold_in(key, 1), hparams, count)
        if params_key == "effects":
            params = anneal.effect_ramp(params, sim.effects.sites, state.epoch, *ramp, delay)
        episodes = starts is None  # given starts: branches, mid-episode
        starts, visited, actions, rewards, k_improve = collect(
            engine, params, count, state.policy, hparams, state.epoch, key, drawn, starts
        )
        obs, result, alpha = improve_batch(
            engine,
            params,
            state.policy,
            hparams,
            state.epoch,
            starts,
            visited,
            actions,
            k_improve,
            drawn,
            episodes,
        )
        return obs, result, rewards.sum(-1), alpha, visited

    def epoch(state: TrainState, hparams):
        # the same keys whether or not a model takes part: a run with beta = 0 in a beta sweep
        # is the run without a model
        key, sim_key, regress_key, model_key = jax.random.split(state.key, 4)
        delay = ramp_delay(state)
        ramp_share = anneal.ramp_share(state.epoch, *ramp, delay)
        n_sim, masks, rows = shares(hparams, ramp_share)
        outs = [collect_and_improve(env, "effects", parts[0][1], state, hparams, sim_key, delay)]
        if n_model_max:
            starts = None
            if branched:
                k_branch = jax.random.fold_in(model_key, 1)
                starts = branch_starts(outs[0][4], n_sim, parts[1][1], k_branch)
            outs.append(
                collect_and_improve(
                    model, None, parts[1][1], state, hparams, model_key, delay, starts
                )
            )
        obs = jnp.concatenate([o[0].reshape(-1, sim.n_obs) for o in outs])[rows]
        targets = jnp.concatenate([o[1].actions.reshape(-1, sim.n_act) for o in outs])[rows]
        counted = counted_steps(state.epoch)
        weights = None  # the steps the improvement did not count were not improved: left out
        if counted is not None:  # (a branch's steps all count)
            step = jnp.arange(algo.rollouts * horizon)
            weights = counted[step % horizon]
            if branched:
                weights = jnp.where(step < n_sim * horizon, weights, 1.0)
        params, opt_state, loss = regress_batch(
            state.policy, state.opt_state, obs, targets, regress_key, weights=weights
        )

        def used(value_of, part):  # a part's values, NaN where this run does not use them
            return jnp.where(masks[part], value_of(outs[part]), jnp.nan)

        def used_all(value_of):
            return jnp.concatenate([used(value_of, p) for p in range(len(outs))])

        metrics = {
            # the (noisy) policy's return on the simulator
            "return": jnp.nanmean(used(lambda o: o[2], 0)),
            "improved_return": jnp.nanmean(used(lambda o: o[1].new_value, 0)),
            "loss": loss,
            "step_size": outs[0][3],
            "noise": sigma(hparams, state.epoch),
            "accepted": jnp.nanmean(used_all(lambda o: o[1].accepted)),
            "skipped": jnp.nansum(used_all(lambda o: o[1].skipped)),
        }
        if ramp[1]:  # how far the continuation has gone: 0 before it, 1 at its end
            metrics["ramp"] = ramp_share
        progress = track(state, metrics["return"], ramp_share)
        return TrainState(params, opt_state, state.epoch + 1, key, progress), metrics

    chunk = chunk_length(algo.epochs, algo.chunk)

    def run_chunk(state, hparams):
        return jax.lax.scan(lambda s, _: epoch(s, hparams), state, None, length=chunk)

    def train(key, hparams):
        state = init(key, hparams)
        return jax.lax.scan(lambda s, _: epoch(s, hparams), state, None, length=algo.epochs)

    hparams = {
        "step_size": jnp.asarray(algo.step_size, jnp.float32),
        "noise_scale": jnp.asarray(cfg.noise.scale, jnp.float32),
        "noise_decay": jnp.asarray(cfg.noise.decay, jnp.float32),
        "beta": jnp.asarray(cfg.dynamics.beta, jnp.float32),
        "effects": env.params,
    }
    if randomized:
        hparams |= randomization.hparams()
    stages = Stages(
        functools.partial(collect, env), functools.partial(improve_batch, env), regress_batch
    )
    return Trainer(init, run_chunk, train, final_policy, chunk, policy, hparams, stages)
