"""Learned dynamics models (hds.dynamics) on a cart-pole plant with 20 N of Coulomb friction on
the slider, which the simulator does not know: every model beats constant velocity on held-out
episodes, the residual model with zero correction is the simulator, the ensemble is less sure
off its data, models survive a save/load round trip and refuse another system, and a model
drives rollouts inside the PODS/HDS trainer.

Budgets are small; each model is fitted once per module and the trainer compiled once."""

from __future__ import annotations

from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hds import dynamics
from hds.config import EffectConfig
from hds.envs import make_env
from tests.conftest import make_config, train_in_chunks, trained

# The analytic backend (MuJoCo-exact cart-pole, compiles in seconds); the models do not depend
# on the backend (the residual one on generalized was checked once: 210 s to compile the trainer).
SMALL = (
    "env.backend=analytic",
    "dynamics.hidden=[64,64]",
    "dynamics.epochs=300",
    "dynamics.minibatch=64",
    "dynamics.ensemble_size=3",
    "dynamics.episodes=32",
    "dynamics.horizon=50",
    "dynamics.eval_steps=[1,10,25]",
    "dynamics.beta=0.5",
    "dynamics.model=mlp",
    # the trainer, for the one HDS test: tiny
    "algo.epochs=2",
    "algo.chunk=2",
    "algo.rollouts=4",
    "env.task.horizon=10",
    "algo.inner_epochs=1",
    "logger=none",
)
FRICTION = [EffectConfig("coulomb_friction", "slider", {"force": 20.0})]
KS = (1, 10, 25)


@pytest.fixture(scope="module")
def setup():
    from hds.real.brax_plant import BraxPlant

    cfg = make_config(*SMALL)
    env = make_env(cfg.env)
    plant = BraxPlant(make_env(cfg.env, effects=FRICTION, sharpness=None))
    train = dynamics.collect_data(cfg.dynamics, env, plant, jax.random.PRNGKey(0))
    test = dynamics.collect_data(
        replace(cfg.dynamics, episodes=8), env, plant, jax.random.PRNGKey(1)
    )
    return cfg, env, plant, train, test


@pytest.fixture(scope="module")
def fitted(setup, tmp_path_factory):
    """kind -> (model, report), fitted lazily: mlp through `build` (collect, fit, save, as the
    run script does), ensemble on the training data plus an episode with NaN, residual plain."""
    cfg, env, plant, train, _ = setup
    cache = {}

    def get(kind):
        if kind in cache:
            return cache[kind]
        dcfg = replace(cfg.dynamics, model=kind)
        if kind == "mlp":
            out = tmp_path_factory.mktemp("built") / "dynamics"
            cache[kind] = dynamics.build(dcfg, env, plant, jax.random.PRNGKey(2), out)
        elif kind == "ensemble":
            obs = np.concatenate([train.obs, train.obs[:1]])
            obs[-1, 5, 1] = np.nan  # one broken episode: dropped, not fitted on
            actions = np.concatenate([train.actions, train.actions[:1]])
            cache[kind] = dynamics.fit(
                dcfg, env, obs, actions, jax.random.PRNGKey(3), compare_simulator=False
            )
        else:
            cache[kind] = dynamics.fit(dcfg, env, train, key=jax.random.PRNGKey(4))
        return cache[kind]

    return get


@pytest.mark.parametrize("kind", ["mlp", "ensemble", "residual"])
def test_every_model_beats_constant_velocity_on_held_out_episodes(setup, fitted, kind):
    _, env, _, _, test = setup
    model, report = fitted(kind)
    errors = dynamics.evaluate(model, test.obs, test.actions, KS)
    for k in map(str, KS):
        ours, base = errors[k]["model"], errors[k]["baseline"]
        assert ours is not None and ours < 0.5 * base, (kind, k, ours, base)
        # the fit's own report (validation episodes) says the same
        assert report["multistep"][k]["model"] < report["multistep"][k]["baseline"]
    assert errors["25"]["model"] < 0.4 * errors["25"]["baseline"]
    # normalised targets: predicting their mean scores 1; each member's best does far better
    assert all(v is not None and 0 < v < 0.5 for v in report["val_loss"]), report["val_loss"]
    assert report["epochs_run"][0] > report["best_epoch"][0] >= 0


def test_the_residual_model_closes_the_simulators_gap(fitted):
    """The simulator knows no friction: the residual model must do better than it alone."""
    _, report = fitted("residual")
    for k in map(str, KS):
        row = report["multistep"][k]
        assert row["model"] < 0.5 * row["simulator"], (k, row)


def test_residual_with_zero_correction_is_the_simulator(setup):
    from hds.algo.rollout import trajectory

    cfg, env, *_ = setup
    model = dynamics.skeleton("residual", env, [16], 1)  # fresh init: the last layer is zero
    assert np.all(np.asarray(jax.vmap(model.deltas)(jnp.ones((3, 4)), jnp.ones((3, 1)))) == 0)
    key = jax.random.PRNGKey(5)
    actions = jax.random.uniform(key, (20, 1), minval=-1.0, maxval=1.0)
    sim_states, sim_rewards = jax.jit(
        lambda a: trajectory(env, env.params, env.task, env.reset(key), a)
    )(actions)
    model_states, model_rewards = jax.jit(
        lambda a: trajectory(model, None, env.task, model.reset(key), a)
    )(actions)
    np.testing.assert_allclose(model_states, sim_states, atol=2e-4, rtol=1e-4)
    np.testing.assert_allclose(model_rewards, sim_rewards, atol=1e-3, rtol=1e-4)


DELAY = [EffectConfig("action_delay", "slide", {"steps": 2})]
LAG = [EffectConfig("actuator_lag", "slide", {"time_constant": 0.05})]


def _assert_same_trajectory(env, model):
    """The model (zero correction) follows env's simulator step for step from one state."""
    from hds.algo.rollout import trajectory

    key = jax.random.PRNGKey(5)
    actions = jax.random.uniform(key, (20, 1), minval=-1.0, maxval=1.0)
    sim_states, _ = jax.jit(lambda a: trajectory(env, env.params, env.task, env.reset(key), a))(
        actions
    )
    model_states, _ = jax.jit(lambda a: trajectory(model, None, env.task, model.reset(key), a))(
        actions
    )
    np.testing.assert_allclose(model_states, sim_states, atol=2e-4, rtol=1e-4)


def test_a_residual_model_carries_its_simulator_s_delay_from_step_to_step(setup):
    """On a simulator with a delay (and friction), the residual model with zero correction is
    still that simulator along a whole trajectory: the delay's buffer is in the model's state
    (restarted at rest each step, every delayed control would be 0)."""
    cfg, *_ = setup
    env = make_env(cfg.env, effects=DELAY + FRICTION)
    model = dynamics.skeleton("residual", env, [16], 1)
    assert model.delays == ((0, 2),) and model.history == 2
    _assert_same_trajectory(env, model)
    # a step after rest applies nothing yet: the cart is where friction and gravity leave it
    assert model.applied_actions(np.ones((1, 3, 1)))[0, :, 0].tolist() == [0.0, 0.0, 1.0]


def test_a_residual_model_carries_its_simulator_s_lag_filter_from_step_to_step(setup):
    """On a simulator with an actuator lag (and a delay, and friction), the residual model with
    zero correction is still that simulator along a whole trajectory: the lag's filter is in
    the model's state, as the delay's buffer is. Restarted at rest each step, the 50 ms filter
    would pass on a third of each control at most."""
    cfg, *_ = setup
    env = make_env(cfg.env, effects=LAG + DELAY + FRICTION)
    model = dynamics.skeleton("residual", env, [16], 1)
    assert model.n_effect_state == 1 and model.history == 2
    _assert_same_trajectory(env, model)


def test_branched_rollouts_start_a_lagged_model_from_its_state_not_a_bare_observation(setup):
    """A branch starts from a visited observation: the trainer makes it the model's state
    (`start`: the lag's filter at rest), where a bare observation is refused by the step."""
    from hds.algo.pods import make_train_from_config

    cfg, *_ = setup
    env = make_env(cfg.env, effects=LAG)
    model = dynamics.zero_residual(env)
    obs = jnp.zeros(model.n_obs)
    with pytest.raises(ValueError, match="model.start"):
        model.step(obs, jnp.zeros(1))
    assert model.step(model.start(obs), jnp.zeros(1)).shape == (model.n_obs + 1,)
    branched = replace(cfg, dynamics=replace(cfg.dynamics, branch=5))
    trainer = make_train_from_config(branched, env, model)
    key, hparams = jax.random.PRNGKey(0), trainer.default_hparams
    jax.eval_shape(trainer.train, key, hparams)  # traced only: the shapes are what is checked


@pytest.mark.parametrize("effects", [DELAY, LAG + DELAY], ids=["delay", "lag"])
def test_the_simulator_s_k_step_error_on_its_own_episodes_is_nil(setup, effects, caplog):
    """hds.dynamics.evaluate starts each window's delay buffer from the controls recorded
    before it, and its lag filter where those controls left it (the filter run along the
    episode): on episodes of the simulator itself, its k-step error is its float error only,
    and the model's (zero correction) the same. Fitted on them, each target is the plant's
    step less the simulator's from that state: nothing to correct, so nothing is learned.
    The filter's program is compiled once for the fit and both evaluations (the model's and
    the simulator's, on fewer episodes): it depends on the env's simulator, less its delays,
    alone."""
    from hds.real.brax_plant import BraxPlant

    cfg, *_ = setup
    env = make_env(cfg.env, effects=effects)
    plant = BraxPlant(make_env(cfg.env, effects=effects, sharpness=None))
    data = dynamics.collect_data(
        replace(cfg.dynamics, episodes=4), env, plant, jax.random.PRNGKey(2)
    )
    model = dynamics.skeleton("residual", env, [16], 1)
    with jax.log_compiles(), caplog.at_level("WARNING", logger="jax"):
        errors = dynamics.evaluate(model, data.obs, data.actions, KS, env)
        _, report = dynamics.fit(
            replace(cfg.dynamics, model="residual", epochs=5), env, data, key=jax.random.PRNGKey(3)
        )
    for k in KS:
        assert errors[str(k)]["simulator"] < 1e-3, (k, errors[str(k)])
        assert errors[str(k)]["model"] < 1e-3, (k, errors[str(k)])
        assert errors[str(k)]["baseline"] > 0.01, (k, errors[str(k)])  # the data do move
    for k in ("1", "10"):
        assert report["multistep"][k]["model"] < 1e-3, (k, report["multistep"][k])
    compiled = [r for r in caplog.messages if r.startswith("Compiling jit(_effect_states_along)")]
    assert len(compiled) == model.n_effect_state


def test_ensemble_disagrees_more_off_its_data(setup, fitted):
    *_, test = setup
    model, report = fitted("ensemble")
    assert model.members == 3 and report["members"] == 3
    assert report["disagreement"] > 0
    o = jnp.asarray(test.obs[:, :-1].reshape(-1, 4), jnp.float32)
    u = jnp.asarray(test.actions.reshape(-1, 1), jnp.float32)
    spread = jax.jit(jax.vmap(model.disagreement))
    on = float(jnp.mean(spread(o, u)))
    # off the data: velocities five times larger, full-range pushes (the data reach 20 %)
    off_o = o.at[:, 2:].multiply(5.0)
    off_u = 3.0 * jnp.sign(u + 1e-6)
    off = float(jnp.mean(spread(off_o, off_u)))
    assert off > 3 * on, (on, off)
    members = np.asarray(jax.vmap(model.predict_members)(o[:8], u[:8]))
    assert not np.allclose(members[:, 0], members[:, 1])  # members differ


def test_nan_episodes_are_dropped_not_fitted(setup, fitted):
    _, _, _, train, _ = setup
    model, report = fitted("ensemble")
    assert sum(report["episodes"].values()) == train.n_episodes  # the broken one is gone
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(model.params))


def test_training_skips_non_finite_minibatches_and_keeps_the_best():
    """Rows with NaN targets poison some minibatches: those steps are skipped, the rest learn."""
    from hds.dynamics.model import MLP, init_params
    from hds.dynamics.training import train_members

    rng = np.random.default_rng(0)
    x = rng.normal(size=(256, 3)).astype(np.float32)
    y = np.sin(x[:, :1]) + 0.5 * x[:, 1:2]
    x_val, y_val = x[:64], y[:64].copy()
    y = y.copy()
    y[::50] = np.nan  # 6 bad rows: about one minibatch in five holds one
    net = MLP((16,), 1)
    params = init_params(net, jax.random.PRNGKey(0), 3, 2)
    best, info = train_members(
        net,
        params,
        x,
        y,
        x_val,
        y_val,
        jax.random.split(jax.random.PRNGKey(1), 2),
        learning_rate=1e-2,
        minibatch=32,
        epochs=40,
        patience=40,
    )
    assert all(bool(jnp.all(jnp.isfinite(a))) for a in jax.tree.leaves(best))
    history = np.asarray(info["history"])  # [members, epochs, (train, val)]
    assert np.all(np.isfinite(history[..., 1]))
    assert np.all(np.asarray(info["best_val"]) < 0.2 * history[:, 0, 1])
    # the kept parameters are the best epoch's: their validation loss is the minimum seen
    np.testing.assert_allclose(np.asarray(info["best_val"]), np.nanmin(history[..., 1], axis=1))


@pytest.mark.parametrize("kind", ["mlp", "ensemble", "residual"])
def test_save_load_round_trip_predicts_identically(setup, fitted, tmp_path, kind):
    cfg, env, _, _, test = setup
    model, report = fitted(kind)
    if kind == "mlp":  # build saved it already
        path = report["path"]
        assert report["loaded"] is False and report["data"] == "plant"
    else:
        path = dynamics.save(tmp_path / kind, model, replace(cfg.dynamics, model=kind), report)
    loaded = dynamics.load(path, env)
    assert loaded.kind == kind and loaded.members == model.members
    for a, b in zip(
        jax.tree.leaves((model.params, model.norm)),
        jax.tree.leaves((loaded.params, loaded.norm)),
        strict=True,
    ):
        np.testing.assert_array_equal(a, b)
    o = jnp.asarray(test.obs[:2, :-1].reshape(-1, 4), jnp.float32)
    u = jnp.asarray(test.actions[:2].reshape(-1, 1), jnp.float32)
    # the network's output (for residual, the simulator's step is added to it: same env)
    np.testing.assert_array_equal(
        np.asarray(jax.vmap(loaded.deltas)(o, u)), np.asarray(jax.vmap(model.deltas)(o, u))
    )
    if kind != "residual":  # the whole step (eagerly: cheap without a simulator in it)
        np.testing.assert_array_equal(
            np.asarray(jax.vmap(loaded.predict)(o, u)), np.asarray(jax.vmap(model.predict)(o, u))
        )
    meta = dynamics.read_meta(path)
    assert meta["config"]["model"] == kind
    assert meta["report"]["multistep"] == report["multistep"]


def test_a_model_no_better_than_the_simulator_is_not_used(setup, fitted, tmp_path):
    """On a plant that is the simulator itself nothing is left to learn: the fitted model
    predicts worse than the simulator, so build returns no model and says why; on the 20 N
    friction plant it beats the simulator at every k and is used."""
    from hds.real.brax_plant import BraxPlant

    cfg, env, *_ = setup
    _, report = fitted("mlp")
    assert report["used"] is True and "not_used_because" not in report
    same = BraxPlant(make_env(cfg.env, effects=[], sharpness=None))
    model, report = dynamics.build(cfg.dynamics, env, same, jax.random.PRNGKey(2), tmp_path)
    assert model is None and report["used"] is False
    assert "k=1:" in report["not_used_because"] and "k=25:" in report["not_used_because"]
    kept, _ = dynamics.build(
        replace(cfg.dynamics, require_better=False), env, same, jax.random.PRNGKey(2), tmp_path
    )
    assert kept is not None


@pytest.mark.parametrize(
    "errors, worse",
    [
        ({"1": (0.01, 0.02), "25": (0.1, 0.2)}, []),
        ({"1": (0.03, 0.02), "25": (0.1, 0.2)}, ["k=1"]),
        ({"1": (None, 0.02), "25": (0.3, 0.2)}, ["k=1", "k=25"]),
        ({"1": (0.03, None)}, []),  # the simulator's own prediction was not finite
    ],
)
def test_worse_than_simulator_names_each_k_the_model_does_not_beat(errors, worse):
    report = {"multistep": {k: {"model": m, "simulator": s} for k, (m, s) in errors.items()}}
    why = dynamics.worse_than_simulator(report)
    if not worse:
        assert why is None
    else:
        assert [k for k in ("k=1", "k=25") if f"{k}:" in why] == worse


def test_build_reuses_a_saved_model_by_path(setup, fitted):
    cfg, env, *_ = setup
    _, report = fitted("mlp")
    model, again = dynamics.build(
        replace(cfg.dynamics, path=report["path"]), env, None, jax.random.PRNGKey(0), "/nonexistent"
    )
    assert again["loaded"] is True and again["multistep"] == report["multistep"]


def test_loading_a_missing_path_says_where_and_how(setup, tmp_path):
    env = setup[1]
    missing = tmp_path / "no_model_here"
    with pytest.raises(FileNotFoundError, match="no_model_here.*does not exist.*hds.run"):
        dynamics.load(missing, env)
    missing.mkdir()
    with pytest.raises(FileNotFoundError, match="holds no saved dynamics model"):
        dynamics.load(missing, env)


def test_a_model_of_another_system_is_refused(setup, fitted, tmp_path):
    cfg = setup[0]
    _, report = fitted("mlp")
    pendulum = make_env(make_config("env=pendulum_swingup", "real=none").env)
    with pytest.raises(ValueError, match=r"another system.*obs_names.*q_hinge"):
        dynamics.load(report["path"], pendulum)
    slower = make_env(replace(cfg.env, frames_per_step=4))
    with pytest.raises(ValueError, match=r"another system.*dt = 0.04"):
        dynamics.load(report["path"], slower)


def test_dynamics_configs_compose_and_bad_values_are_named():
    for kind in ("mlp", "ensemble", "residual"):
        dcfg = make_config(f"dynamics={kind}").dynamics
        assert dcfg.model == kind and dcfg.beta == 0.25
    with pytest.raises(ValueError, match="dynamics.val_fraction"):
        make_config("dynamics=mlp", "dynamics.val_fraction=0")
    with pytest.raises(ValueError, match="dynamics.excitation"):
        make_config("dynamics=mlp", "dynamics.excitation=noise")


@pytest.fixture(scope="module")
def through_model(setup, fitted):
    """dynamics.branch -> (policy before, state, metrics) of the trainer through the ensemble
    (key 0), trained once per branch for the tests below."""
    from hds.algo.pods import make_train_from_config

    cfg, env, *_ = setup
    model, _ = fitted("ensemble")
    cache = {}

    def get(branch):
        if branch not in cache:
            branched = replace(cfg, dynamics=replace(cfg.dynamics, branch=branch))
            trainer = make_train_from_config(branched, env, model)
            key, hparams = jax.random.PRNGKey(0), trainer.default_hparams
            before = trainer.init(key, hparams).policy
            cache[branch] = (before, *jax.jit(trainer.train)(key, hparams))
        return cache[branch]

    return get


def test_a_model_drives_rollouts_inside_the_trainer(setup, through_model):
    from hds.algo.pods import make_train_from_config

    cfg, env, *_ = setup
    before, state, metrics = through_model(cfg.dynamics.branch)
    assert np.all(np.isfinite(np.asarray(metrics["return"])))
    assert np.all(np.isfinite(np.asarray(metrics["loss"])))
    assert int(np.sum(metrics["skipped"])) == 0
    changed = [
        not np.array_equal(a, b)
        for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(state.policy), strict=True)
    ]
    assert all(changed)
    # the model's share of the rollouts matters: without it (the same key: cfg's seed 0)
    # training differs; trained through the suite's programs of these shapes (conftest.TINY's)
    assert cfg.seed == 0 and cfg.seeds == 1
    state_alone, _ = train_in_chunks(cfg, make_train_from_config(cfg, env))
    first, first_alone = jax.tree.leaves(state.policy)[0], jax.tree.leaves(state_alone.policy)[0][0]
    assert not np.allclose(first, first_alone)


def test_branched_model_rollouts_start_from_states_the_used_simulator_rollouts_visited():
    """dynamics.branch's starts: only states of the rollouts this run uses (the first
    n_used), from every one of them and from many steps; more draws begin with the same ones."""
    from hds.algo.pods import branch_starts

    n, steps, n_used = 6, 10, 3
    visited = jnp.arange(n * steps * 4, dtype=jnp.float32).reshape(n, steps, 4)
    key = jax.random.PRNGKey(3)
    starts = np.asarray(jax.jit(branch_starts, static_argnums=2)(visited, n_used, 300, key))
    flat = np.asarray(visited).reshape(-1, 4)
    index = [int(np.flatnonzero((flat == s).all(1))[0]) for s in starts]
    rollout, step = np.divmod(index, steps)
    assert set(rollout) == set(range(n_used))
    assert len(set(step)) == steps
    fewer = np.asarray(branch_starts(visited, n_used, 40, key))
    np.testing.assert_array_equal(fewer, starts[:40])


def test_branched_starts_give_a_delayed_model_the_controls_commanded_before_them():
    from hds.algo.pods import branch_starts

    n, steps, history = 4, 6, 2
    visited = jnp.arange(n * steps * 4, dtype=jnp.float32).reshape(n, steps, 4)
    commanded = -1.0 - jnp.arange(n * steps, dtype=jnp.float32).reshape(n, steps, 1)
    key = jax.random.PRNGKey(3)
    starts, before = branch_starts(visited, n, 60, key, commanded, history)
    np.testing.assert_array_equal(starts, branch_starts(visited, n, 60, key))  # same draws
    flat = np.asarray(visited).reshape(-1, 4)
    for start, got in zip(np.asarray(starts), np.asarray(before), strict=True):
        rollout, step = divmod(int(np.flatnonzero((flat == start).all(1))[0]), steps)
        padded = np.concatenate([np.zeros((history, 1)), np.asarray(commanded[rollout])])
        np.testing.assert_array_equal(got, padded[step : step + history])


def test_a_branch_through_the_delayed_simulator_s_model_continues_the_simulator_s_rollout(setup):
    """A branched rollout starts where a simulator rollout was, its delay buffer holding the
    controls commanded before (branch_starts, DynamicsModel.start): through the residual model
    with zero correction it goes on as the simulator's rollout did; the trainer runs on it."""
    from hds.algo.pods import branch_starts, make_train_from_config
    from hds.algo.rollout import trajectory

    cfg, *_ = setup
    env = make_env(cfg.env, effects=DELAY)
    model = dynamics.skeleton("residual", env, [16], 1)
    key = jax.random.PRNGKey(7)
    commanded = jax.random.uniform(key, (3, 12, 1), minval=-1.0, maxval=1.0)

    def visited(k, actions):  # the observations before each step, as a policy rollout's
        start = env.reset(k)
        states = trajectory(env, env.params, env.task, start, actions)[0]
        return jnp.concatenate([env.observe(start, env.params)[None], states[:-1]])

    obs = jax.jit(jax.vmap(visited))(jax.random.split(key, 3), commanded)
    starts, before = branch_starts(obs, 3, 8, key, commanded, model.history)
    flat = np.asarray(obs).reshape(-1, obs.shape[-1])
    for start, previous in zip(starts, before, strict=True):
        which, when = divmod(int(np.flatnonzero((flat == np.asarray(start)).all(1))[0]), 12)
        if when > 8:
            continue
        state = model.start(start, previous)
        went = trajectory(model, None, env.task, state, commanded[which, when : when + 3])[0]
        np.testing.assert_allclose(went, obs[which, when + 1 : when + 4], atol=2e-4, rtol=1e-4)
    branched = replace(cfg, dynamics=replace(cfg.dynamics, branch=5))
    trainer = make_train_from_config(branched, env, model)
    _, metrics = jax.jit(trainer.train)(key, trainer.default_hparams)
    assert np.all(np.isfinite(np.asarray(metrics["loss"])))


def test_the_builds_model_counts_in_numpy_are_the_traced_counts():
    """Split.of counts the model's rollouts in numpy (no eager jax op at build time); the
    traced epoch counts them in jax: the same float32 rounding (half to even) for every share."""
    from hds.algo.pods import _model_count

    shares = np.linspace(0.0, 1.0, 201, dtype=np.float64).tolist() + [0.125, 0.375, 1 / 3]
    for rollouts in (1, 3, 8, 50, 64, 1000):
        built = [int(_model_count(b, rollouts, np)) for b in shares]
        traced = jax.jit(jax.vmap(lambda b, r=rollouts: _model_count(b, r)))(np.float32(shares))
        assert built == np.asarray(traced).tolist()


# make test-slow: a second compile of the trainer through the model; make test keeps branch 0
# (test_a_model_drives_rollouts_inside_the_trainer)
@pytest.mark.slow
def test_branched_model_rollouts_drive_the_trainer(through_model):
    """dynamics.branch=5 (of a 10-step horizon): training through the model stays finite,
    and its short rollouts from simulator states train otherwise than whole ones."""
    results = {}
    for branch in (0, 5):
        _, state, metrics = through_model(branch)
        assert np.all(np.isfinite(np.asarray(metrics["loss"])))
        assert int(np.sum(metrics["skipped"])) == 0
        results[branch] = jax.tree.leaves(state.policy)[0]
    assert not np.allclose(results[0], results[5])


@pytest.mark.parametrize("kind", ["mlp", "ensemble"])
def test_model_rollouts_have_a_finite_nonzero_action_gradient(setup, fitted, kind):
    from hds.algo.rollout import open_loop_return

    env = setup[1]
    model, _ = fitted(kind)
    start = model.reset(jax.random.PRNGKey(6))
    grad = jax.jit(jax.grad(lambda a: open_loop_return(model, None, env.task, start, a)))(
        jnp.zeros((10, 1))
    )
    assert np.all(np.isfinite(np.asarray(grad))) and float(jnp.abs(grad).min()) > 0


def test_residual_step_has_a_finite_jacobian(setup, fitted):
    """Through the simulator's re-initialisation at (q, qd) and its step, plus the network.
    (No finite-difference comparison: the learned dry friction is steep near zero velocity,
    where a central difference of 1e-2 is off by 7 % while the simulator alone agrees.)"""
    *_, test = setup
    model, _ = fitted("residual")
    x = jnp.concatenate(
        [jnp.asarray(test.obs[0, 10], jnp.float32), jnp.asarray(test.actions[0, 10], jnp.float32)]
    )
    jac = np.asarray(jax.jit(jax.jacrev(lambda x: model.step(x[:4], x[4:])))(x))
    assert np.all(np.isfinite(jac)) and np.all(np.abs(jac).max(0) > 0)


def test_the_simulator_gradient_is_the_base_step_s_jacobian_at_the_corrected_step(
    setup, fitted, tmp_path
):
    """dynamics.gradient=simulator: the same next state as the fitted residual model's, and the
    Jacobian of its base (the simulator's step) where the model's own differs from it."""
    cfg, env, *_, test = setup
    model, _ = fitted("residual")
    own = replace(model, gradient="simulator")
    x = jnp.concatenate(
        [jnp.asarray(test.obs[0, 10], jnp.float32), jnp.asarray(test.actions[0, 10], jnp.float32)]
    )

    def jacobian(m, f):
        return np.asarray(jax.jit(jax.jacrev(lambda x: f(m, x[:4], x[4:])))(x))

    def step(m, o, u):
        return m.step(o, u)

    def base(m, o, u):
        return m.base(o, u)

    assert np.array_equal(
        np.asarray(jax.jit(lambda x: own.step(x[:4], x[4:]))(x)),
        np.asarray(jax.jit(lambda x: model.step(x[:4], x[4:]))(x)),
    )
    np.testing.assert_allclose(jacobian(own, step), jacobian(model, base), rtol=1e-6, atol=1e-7)
    assert not np.allclose(jacobian(model, step), jacobian(model, base), rtol=1e-3, atol=1e-5)
    # the setting is the run's, not the fit's: build hands it to a saved model it loads
    dcfg = replace(cfg.dynamics, model="residual", gradient="simulator")
    path = dynamics.save(tmp_path / "dynamics", model, dcfg, {})
    built, _ = dynamics.build(replace(dcfg, path=str(path)), env, None, None, "/nonexistent")
    assert built.gradient == "simulator" and model.gradient == "model"
    with pytest.raises(ValueError, match="dynamics.gradient = simulator needs a simulator"):
        make_config("dynamics=mlp", "dynamics.gradient=simulator")


@pytest.mark.slow  # make test-slow: keeps make test under 10 min cold
@pytest.mark.parametrize("branch", [0, 5])
def test_a_vmapped_beta_sweep_gives_the_numbers_of_separate_runs(setup, fitted, tmp_path, branch):
    """sweep.beta trains every share of model rollouts in one program (the widest split, each
    run using its own share): the numbers of one run per beta, beta = 0 being plain PODS;
    with whole model rollouts and with branched ones."""
    _, env, *_ = setup
    model, _ = fitted("ensemble")
    betas = (0.0, 0.25, 0.75)
    small = (*SMALL, f"dynamics.branch={branch}")
    swept = make_config(*small, f"sweep.beta=[{','.join(map(str, betas))}]")
    together, history = trained(swept, env, tmp_path / "vmapped", "hds", model)
    for i, beta in enumerate(betas):
        alone_cfg = make_config(*small, f"dynamics.beta={beta}")
        alone, alone_history = trained(
            alone_cfg, env, tmp_path / f"alone{i}", "hds", model if beta else None
        )
        for a, b in zip(jax.tree.leaves(together), jax.tree.leaves(alone), strict=True):
            np.testing.assert_allclose(a[i], b[0], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(history["return"][i], alone_history["return"][0], rtol=1e-5)
    first = [np.asarray(jax.tree.leaves(together)[0][i]) for i in range(len(betas))]
    assert not np.allclose(first[1], first[2])  # the share matters


@pytest.mark.slow  # make test-slow: keeps make test under 10 min cold
def test_the_model_share_grows_in_with_the_effect_ramp(setup, fitted, tmp_path):
    """anneal.effect_ramp=[0.5, 0.75] of 4 epochs: no rollout through the model in epochs 0
    and 1 (the run without a model, to the bit), then dynamics.beta of them."""
    _, env, *_ = setup
    model, _ = fitted("mlp")
    ramp = ("algo.epochs=4", "anneal.effect_ramp=[0.5,0.75]")
    _, ramped = trained(make_config(*SMALL, *ramp), env, tmp_path / "ramped", "hds", model)
    _, alone = trained(
        make_config(*SMALL, *ramp, "dynamics.beta=0"), env, tmp_path / "alone", "hds", None
    )
    np.testing.assert_array_equal(ramped["loss"][0][:2], alone["loss"][0][:2])
    assert not np.allclose(ramped["loss"][0][2:], alone["loss"][0][2:])


def test_branched_model_rollouts_need_simulator_rollouts_to_branch_from():
    with pytest.raises(ValueError, match=r"dynamics.branch = 5 .* beta of 1 leaves none"):
        make_config("method=hds", "dynamics.beta=1.0")
    assert make_config("method=hds", "dynamics.beta=1.0", "dynamics.branch=0").dynamics.beta == 1


def test_a_beta_sweep_needs_a_model():
    with pytest.raises(ValueError, match="sweep.beta.*dynamics.model = none"):
        make_config("sweep.beta=[0.1,0.2]")
    with pytest.raises(ValueError, match=r"sweep.beta = \[0.5, 2.0\] must lie in \[0, 1\]"):
        make_config("dynamics=mlp", "sweep.beta=[0.5,2.0]")


def test_a_policy_run_through_a_model_that_is_the_plant_scores_the_plants_return(setup):
    """closed_loop_returns: through a model that is the plant a policy scores its return on
    the plant, from the same initial states; on a plant with friction it does not."""
    from hds.data import initial_states
    from hds.real import rollout
    from hds.real.brax_plant import BraxPlant

    cfg, env, friction_plant, _, _ = setup
    gains = np.array([[0.5], [8.0], [0.5], [1.0]])

    def policy(o):  # a feedback that pushes the cart under the pole; NumPy or JAX
        xp = jnp if isinstance(o, jax.Array) else np
        return 2.0 * xp.tanh(o @ gains)

    q0, qd0 = initial_states(env.task, 5, 6)
    exact = dynamics.zero_residual(env)  # the simulator's own step
    through = dynamics.closed_loop_returns(
        exact, env.task, policy, np.concatenate([q0, qd0], 1), 40, env.sim.ctrl_range
    )
    assert through.shape == (6,) and np.all(through < 0)
    plain = BraxPlant(make_env(cfg.env, sharpness=None))
    for plant, same in ((plain, True), (friction_plant, False)):
        on_plant = rollout(plant, env.task, q0, qd0, policy, 40).returns
        assert np.allclose(through, on_plant, rtol=1e-3) is same, (through, on_plant)
