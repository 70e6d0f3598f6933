"""Fit a dynamics model on measured episodes: one-step prediction error, Adam, early stopping.

The data are E episodes, obs [E, T+1, n_obs] and actions [E, T, n_act], with transition
(obs[e, t], actions[e, t]) -> obs[e, t+1]. Episodes (not transitions) are split into training
and validation, so validation measures generalisation to new trajectories.

Training is one compiled program per fit: a `lax.while_loop` over epochs (stopping after
`patience` epochs without a better validation loss, or at `epochs`) around a `lax.scan` over
shuffled minibatches; the K members of an ensemble are vmapped through it, each with its own
initialisation and data order. The parameters with the best validation loss are kept. A
minibatch whose loss or gradient is not finite is skipped; a non-finite validation loss never
counts as an improvement.
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import optax

from hds.data.budget import DYNAMICS_FIT, Progress
from hds.data.format import split_episodes
from hds.dynamics.metrics import multistep_errors
from hds.dynamics.model import (
    DynamicsModel,
    Normalizer,
    constant_velocity,
    init_params,
    skeleton,
    wrap_angles,
    zero_residual,
)
from hds.utils.shuffle import permutation

log = logging.getLogger(__name__)


def as_arrays(data, actions=None, sim=None) -> tuple[np.ndarray, np.ndarray]:
    """(obs [E, T+1, n_obs], actions [E, T, n_act]) as float32 from arrays or a Dataset (anything
    with .obs and .actions), checked against the system's sizes and, when the data carry names,
    its observation and action names."""
    if actions is None:
        if not (hasattr(data, "obs") and hasattr(data, "actions")):
            raise TypeError("give obs and actions arrays, or a Dataset (with .obs and .actions)")
        if sim is not None and hasattr(data, "dt"):
            from hds.data import validate

            validate(data, sim)  # names and their order, finite values, control range, dt
            if not np.isclose(float(data.dt), sim.dt, rtol=1e-6):
                raise ValueError(
                    f"the dataset is sampled every {data.dt} s and this system steps every "
                    f"{sim.dt} s: a learned model predicts one step of the system, so set "
                    f"env.frames_per_step to {data.dt / sim.timestep:g} (dt / env.timestep), "
                    "or resample the data"
                )
        data, actions = data.obs, data.actions
    with np.errstate(over="ignore"):  # beyond float32: inf, dropped below as non-finite
        obs, actions = np.asarray(data, np.float32), np.asarray(actions, np.float32)
    if (
        obs.ndim != 3
        or actions.ndim != 3
        or obs.shape[0] != actions.shape[0]
        or obs.shape[1] != actions.shape[1] + 1
    ):
        raise ValueError(
            f"obs {obs.shape} and actions {actions.shape} must be [E, T+1, n_obs] "
            "and [E, T, n_act] for the same E episodes (one more observation than "
            "actions per episode)"
        )
    if sim is not None and (obs.shape[2] != sim.n_obs or actions.shape[2] != sim.n_act):
        raise ValueError(
            f"obs have {obs.shape[2]} variables and actions {actions.shape[2]}; "
            f"this system has {sim.n_obs} observations {list(sim.obs_names)} and "
            f"{sim.n_act} actions {list(sim.action_names)}"
        )
    return obs, actions


def _transitions(obs, actions):
    n, m = obs.shape[-1], actions.shape[-1]
    return obs[:, :-1].reshape(-1, n), actions.reshape(-1, m), obs[:, 1:].reshape(-1, n)


def _targets(model: DynamicsModel, base, o, u, o2, chunk: int = 1024) -> np.ndarray:
    """next - base(obs, u), hinge entries wrapped: what the network must predict (of the
    observation; `o` may carry the base's effect states after it). The base (a simulator step
    for residual models) runs in chunks of one padded shape: one compile."""
    n = model.n_obs
    if model.kind != "residual":
        return np.asarray(wrap_angles(jnp.asarray(o2[:, :n] - o[:, :n]), model.angular))
    pad = -len(o) % chunk
    o_pad = np.concatenate([o, np.repeat(o[:1], pad, 0)])
    u_pad = np.concatenate([u, np.repeat(u[:1], pad, 0)])
    parts = [
        np.asarray(base(o_pad[i : i + chunk], u_pad[i : i + chunk]))
        for i in range(0, len(o) + pad, chunk)
    ]
    after = np.concatenate(parts)[: len(o), :n]
    return np.asarray(wrap_angles(jnp.asarray(o2[:, :n] - after), model.angular))


def train_members(
    net, params, x, y, x_val, y_val, keys, *, learning_rate, minibatch, epochs, patience
):
    """Train K members (params stacked on axis 0, one data-order key each) on normalised (x, y);
    returns (best params, info) with info arrays [K]: best_val, best_epoch, epochs_run, and
    history [K, epochs, 2] (mean train loss, validation loss; NaN after the stop)."""
    n = x.shape[0]
    batch = min(minibatch, n)
    n_batches = n // batch
    optimizer = optax.adam(learning_rate)

    def loss_fn(p, xb, yb):
        return jnp.mean((net.apply(p, xb) - yb) ** 2)

    def finite(tree):
        return jnp.all(jnp.array([jnp.all(jnp.isfinite(a)) for a in jax.tree.leaves(tree)]))

    def pick(flag, a, b):
        return jax.tree.map(lambda u, v: jnp.where(flag, u, v), a, b)

    def one(p0, key, x, y, x_val, y_val):  # the data are arguments, not compiled-in constants
        def sgd(carry, idx):
            p, o = carry
            loss, g = jax.value_and_grad(loss_fn)(p, x[idx], y[idx])
            updates, o_new = optimizer.update(g, o, p)
            p_new = optax.apply_updates(p, updates)
            ok = jnp.isfinite(loss) & finite(g) & finite(p_new)
            return (pick(ok, p_new, p), pick(ok, o_new, o)), jnp.where(ok, loss, jnp.nan)

        def body(c):
            key, k = jax.random.split(c["key"])
            perm = permutation(k, n)[: n_batches * batch].reshape(n_batches, batch)
            (p, o), losses = jax.lax.scan(sgd, (c["params"], c["opt"]), perm)
            val = loss_fn(p, x_val, y_val)
            val = jnp.where(jnp.isfinite(val), val, jnp.inf)
            better = val < c["best_val"]
            return {
                "params": p,
                "opt": o,
                "key": key,
                "epoch": c["epoch"] + 1,
                "best": pick(better, p, c["best"]),
                "best_val": jnp.where(better, val, c["best_val"]),
                "best_epoch": jnp.where(better, c["epoch"], c["best_epoch"]),
                "wait": jnp.where(better, 0, c["wait"] + 1),
                "history": c["history"].at[c["epoch"]].set(jnp.stack([jnp.nanmean(losses), val])),
            }

        def more(c):
            return (c["epoch"] < epochs) & (c["wait"] < patience)

        start = {
            "params": p0,
            "opt": optimizer.init(p0),
            "key": key,
            "epoch": jnp.array(0),
            "best": p0,
            "best_val": jnp.where(jnp.isfinite(v := loss_fn(p0, x_val, y_val)), v, jnp.inf),
            "best_epoch": jnp.array(-1),
            "wait": jnp.array(0),
            "history": jnp.full((epochs, 2), jnp.nan),
        }
        c = jax.lax.while_loop(more, body, start)
        info = {k: c[k] for k in ("best_val", "best_epoch", "history")}
        return c["best"], {**info, "epochs_run": c["epoch"]}

    data = [jnp.asarray(a, jnp.float32) for a in (x, y, x_val, y_val)]
    return jax.jit(jax.vmap(one, in_axes=(0, 0, None, None, None, None)))(params, keys, *data)


def fit(
    cfg, env, obs, actions=None, key=None, compare_simulator: bool = True
) -> tuple[DynamicsModel, dict]:
    """Fit `cfg.model` (a DynamicsConfig) for `env`'s system on episodes `obs` [E, T+1, n_obs],
    `actions` [E, T, n_act] (or a Dataset as `obs`). Returns (model engine, report): the report
    (JSON-ready) holds sizes, losses, epochs and the open-loop k-step errors of the model and of
    the constant-velocity baseline on the validation episodes (and, with `compare_simulator`,
    of env's simulator alone: one more compile)."""
    if cfg.model not in ("mlp", "ensemble", "residual"):
        raise ValueError(
            f"dynamics.model = {cfg.model!r} has nothing to fit; choose mlp, ensemble or residual"
        )
    start_time = time.perf_counter()
    key = jax.random.PRNGKey(0) if key is None else key
    obs, actions = as_arrays(obs, actions, env.sim)
    good = np.isfinite(obs).all((1, 2)) & np.isfinite(actions).all((1, 2))
    if not good.any():
        raise ValueError(
            f"all {len(good)} episodes hold NaN or inf values (in float32, beyond "
            f"{np.finfo(np.float32).max:.1e}) and were dropped: nothing is left to fit; repair "
            "or re-record the data"
        )
    if not good.all():
        log.warning(
            "dropping %d of %d episodes with NaN or inf values", int((~good).sum()), len(good)
        )
        obs, actions = obs[good], actions[good]
    # the estimate on the console as it starts (the fit is one compiled program: no stages)
    progress = Progress(DYNAMICS_FIT, obs.shape[0] * (obs.shape[1] - 1), log, cfg.epochs)
    k_split, k_init, k_order = jax.random.split(key, 3)
    seed = int(jax.random.randint(k_split, (), 0, 2**31 - 1))
    train_ep, val_ep = split_episodes(len(obs), cfg.val_fraction, seed, "fitting a model")

    members = int(cfg.ensemble_size) if cfg.model == "ensemble" else 1
    model = skeleton(cfg.model, env, cfg.hidden, members)
    inputs, base = jax.jit(jax.vmap(model.inputs)), jax.jit(jax.vmap(model.base))
    commanded, actions = actions, model.applied_actions(actions)  # what each step applied
    states = model.with_effect_states(obs, actions)  # a lag's filter where the controls left it

    def prepare(episodes):
        o, u, o2 = _transitions(states[episodes], actions[episodes])
        return np.asarray(inputs(o, u)), _targets(model, base, o, u, o2)

    x, y = prepare(train_ep)
    x_val, y_val = prepare(val_ep)
    norm = Normalizer.fit(x, y)
    nx = lambda a: (a - norm.x_mean) / norm.x_std  # noqa: E731
    ny = lambda a: (a - norm.y_mean) / norm.y_std  # noqa: E731

    n_in = x.shape[1]
    params = init_params(model.net, k_init, n_in, members)
    best, info = train_members(
        model.net,
        params,
        nx(x),
        ny(y),
        nx(x_val),
        ny(y_val),
        jax.random.split(k_order, members),
        learning_rate=cfg.learning_rate,
        minibatch=cfg.minibatch,
        epochs=cfg.epochs,
        patience=cfg.patience,
    )
    info = jax.tree.map(np.asarray, info)
    if not np.all(np.isfinite(info["best_val"])):
        raise FloatingPointError(
            "the dynamics model's validation loss never became finite: check the data for "
            "exploding states, or lower dynamics.learning_rate"
        )
    model = replace(model, params=best, norm=norm)
    fit_s = time.perf_counter() - start_time
    progress("fitted")

    at_best = [
        h[int(b), 0] if b >= 0 else np.nan
        for h, b in zip(info["history"], info["best_epoch"], strict=True)
    ]
    report = {
        "model": cfg.model,
        "members": members,
        "hidden": [int(w) for w in cfg.hidden],
        "episodes": {"train": len(train_ep), "validation": len(val_ep)},
        "transitions": {"train": int(len(x)), "validation": int(len(x_val))},
        "epochs_run": [int(e) for e in info["epochs_run"]],
        "best_epoch": [int(e) for e in info["best_epoch"]],
        "train_loss": [_num(v) for v in at_best],  # at the best epoch, normalised units
        "val_loss": [_num(v) for v in info["best_val"]],
        "fit_s": round(fit_s, 2),
    }
    if members > 1:
        spread = jax.jit(jax.vmap(model.disagreement))
        o, u, _ = _transitions(obs[val_ep], actions[val_ep])
        report["disagreement"] = _num(np.mean(np.asarray(spread(o, u))))
    report["multistep"] = evaluate(
        model, obs[val_ep], commanded[val_ep], cfg.eval_steps, env if compare_simulator else None
    )
    report["eval_s"] = round(time.perf_counter() - start_time - fit_s, 2)
    return model, report


def evaluate(model: DynamicsModel, obs, actions, ks, env=None) -> dict:
    """Open-loop k-step errors (nrmse, see hds.dynamics.metrics) of the model and of the
    constant-velocity baseline, and with `env` of its simulator alone (what the model is for:
    the gap it closes): {k: {"model": x, "baseline": x, ["simulator": x,] "model_rmse":
    {name: x}, ...}} (None where a prediction was not finite)."""
    obs, actions = as_arrays(obs, actions)

    # from each measured state a step applies what was applied there (a delayed control from
    # before the window: `applied_actions`), so a delay's buffer is exact in every window, and
    # starts a lag's filter where the controls before it left it (`with_effect_states`)
    def windows(m):
        applied = m.applied_actions(actions)
        return m.predict, m.with_effect_states(obs, applied), applied

    steps = {"model": windows(model)}
    steps["baseline"] = (constant_velocity(model.dt, model.nq), obs, actions)
    if env is not None:
        steps["simulator"] = windows(zero_residual(env))
    rest = (ks, model.angular, model.obs_names)
    errors = {name: multistep_errors(*step, *rest) for name, step in steps.items()}
    out = {}
    for k in errors["model"]:
        row = {name: _num(e[k]["nrmse"]) for name, e in errors.items()}
        for name, e in errors.items():
            row[f"{name}_rmse"] = {n: _num(v) for n, v in e[k]["rmse"].items()}
        out[str(k)] = row
    return out


def _num(value) -> float | None:
    """A JSON-safe float: None for NaN or inf."""
    value = float(value)
    return value if np.isfinite(value) else None
