"""The trainer on the cart-pole: it improves the return, is reproducible, survives NaN gradients,
resumes exactly, and `python -m hds.run` writes every output it promises."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from hds.algo.continuation import Continuation
from hds.algo.improve import ImproveSettings
from hds.algo.pods import (
    Budget,
    Exploration,
    Improvement,
    Regression,
    make_train,
    make_train_from_config,
)
from hds.envs import make_env
from hds.gap import Evaluator
from hds.networks import make_policy
from tests.conftest import FAST, ROOT, make_config, train_in_chunks, trained

# conftest.FAST: conf/debug/fast.yaml, the tests' budget where the policy must learn
TINY = FAST


@pytest.fixture(scope="module")
def setup():
    cfg = make_config(*TINY, "seeds=2")
    env = make_env(cfg.env)
    trainer = make_train_from_config(cfg, env)
    train = lambda: train_in_chunks(cfg, trainer)  # noqa: E731
    keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(2))  # seeds 0 and 1, as cfg.runs()
    state, metrics = train()
    return cfg, env, trainer, train, keys, state, metrics


def test_pods_improves_the_return(setup):
    cfg, env, trainer, _, keys, state, metrics = setup
    evaluator = Evaluator(env, trainer.policy, plant=None, episodes=16)
    before = jax.vmap(trainer.init, in_axes=(0, None))(keys, trainer.default_hparams).policy
    r0 = evaluator.sim_returns(before).mean(axis=1)
    r1 = evaluator.sim_returns(state.policy).mean(axis=1)
    assert np.all(r1 > r0 + 0.1 * np.abs(r0)), (r0, r1)
    assert np.all(np.asarray(metrics["accepted"]) > 0)
    assert int(np.sum(metrics["skipped"])) == 0


def test_a_trainer_built_from_its_parts_trains_as_the_config_s(setup):
    """make_train's parts written by hand for TINY's settings (open-loop PODS, line search, no
    noise, no continuation: docs/trainer.md) make the trainer make_train_from_config builds:
    the same policies to the last bit."""
    cfg, env, _, _, keys, state, _ = setup
    epochs = cfg.algo.epochs
    trainer = make_train(
        env=env,
        policy=make_policy([64, 64], env.sim),
        improvement=Improvement(
            ImproveSettings("first", 1e3, 1e-3, 8, "line_search"), step_size=0.02
        ),
        regression=Regression(optax.adam(1e-3), inner_epochs=4, minibatch=256, early_stop=0.0),
        continuation=Continuation(epochs, horizon=env.task.horizon),
        exploration=Exploration(lambda scale, decay: lambda epoch: jnp.zeros(()), scale=0.0),
        budget=Budget(epochs, rollouts=16, chunk=3),
    )
    built, _ = train_in_chunks(cfg, trainer)
    for a, b in zip(jax.tree.leaves(built.policy), jax.tree.leaves(state.policy), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow  # make test-slow: keeps make test under 10 min cold
def test_more_improvement_steps_reach_better_targets(setup):
    """algo.improve_steps: further line-searched steps from the improved actions. The first
    epoch starts from the same rollouts, and the line search accepts only improvements, so
    every sequence ends at least as high as after one step."""
    cfg, env, trainer, _, keys, _, metrics = setup
    more_cfg = make_config(*TINY, "seeds=2", "algo.improve_steps=3")
    _, more_metrics = train_in_chunks(more_cfg, make_train_from_config(more_cfg, env))
    one, three = (
        np.asarray(metrics["improved_return"])[:, 0],
        np.asarray(more_metrics["improved_return"])[:, 0],
    )
    np.testing.assert_allclose(
        np.asarray(more_metrics["return"])[:, 0], np.asarray(metrics["return"])[:, 0]
    )
    assert np.all(three > one), (one, three)


def test_closed_loop_improvement_trains_and_never_accepts_worse(setup):
    """algo.improve_in=closed_loop: the perturbations u - act(o) replay the rollout exactly,
    the line search keeps every improved closed-loop return at least the rollout's, and the
    policy's return rises."""
    from hds.algo.rollout import perturbed_rollout, policy_rollout

    cfg, env, *_, keys, _, _ = setup
    closed_cfg = make_config(*TINY, "seeds=2", "algo.improve_in=closed_loop", "algo.epochs=30")
    trainer = make_train_from_config(closed_cfg, env)
    state, metrics = train_in_chunks(closed_cfg, trainer)
    assert np.all(np.asarray(metrics["improved_return"]) >= np.asarray(metrics["return"]) - 1e-3)
    evaluator = Evaluator(env, trainer.policy, plant=None, episodes=16)
    before = jax.vmap(trainer.init, in_axes=(0, None))(keys, trainer.default_hparams).policy
    r0, r1 = (evaluator.sim_returns(p).mean(axis=1) for p in (before, state.policy))
    assert np.all(r1 > r0 + 0.1 * np.abs(r0)), (r0, r1)

    params = jax.tree.map(lambda x: x[0], state.policy)
    act = lambda o: trainer.policy.apply(params, o)  # noqa: E731
    low, high = (jnp.asarray(env.sim.ctrl_range[:, i]) for i in (0, 1))
    start = env.reset(jax.random.PRNGKey(3))
    horizon = env.task.horizon
    obs, u, r = policy_rollout(
        env, env.params, env.task, act, start, keys[1], 2.0, horizon, low, high
    )
    deltas = u - jax.vmap(act)(obs)
    replay = perturbed_rollout(env, env.params, env.task, act, start, deltas, low, high)
    np.testing.assert_allclose(replay[0], obs, atol=1e-5)
    np.testing.assert_allclose(replay[2], r, rtol=1e-5, atol=1e-5)


def test_same_seed_same_numbers_and_seeds_differ(setup):
    *_, train, keys, state, metrics = setup
    state2, metrics2 = train()
    for a, b in zip(jax.tree.leaves(state.policy), jax.tree.leaves(state2.policy)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(metrics["return"], metrics2["return"])
    assert not np.array_equal(metrics["return"][0], metrics["return"][1])


@jax.custom_vjp
def poison(u, flag):
    return u


def _poison_fwd(u, flag):
    return u, flag


def _poison_bwd(flag, g):
    return (jnp.where(flag, jnp.nan, 1.0) * g, None)


poison.defvjp(_poison_fwd, _poison_bwd)


@dataclass(frozen=True, eq=False)
class PoisonedEnv:
    """The cart-pole whose action gradient is NaN for episodes starting right of x = 0.25."""

    env: object

    def __getattr__(self, name):
        return getattr(self.env, name)

    def reset(self, key):
        state = self.env.reset(key)
        return state, state.q[0] > 0.25

    def step(self, state, u, params):
        inner, flag = state
        return self.env.step(inner, poison(u, flag), params), flag

    def observe(self, state, params):
        return self.env.observe(state[0], params)

    def qqd(self, state):
        return self.env.qqd(state[0])


def test_a_nan_gradient_is_skipped_and_counted(setup):
    cfg, env = setup[0], setup[1]
    trainer = make_train_from_config(cfg, PoisonedEnv(env))
    state, metrics = train_in_chunks(cfg, trainer)
    skipped = np.asarray(metrics["skipped"])
    assert np.all(skipped > 0) and np.all(skipped < cfg.algo.rollouts)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(state.policy))
    assert np.all(np.isfinite(metrics["loss"]))


def test_kill_and_resume_gives_identical_parameters(tmp_path, monkeypatch):
    from hds.checkpoint import Checkpoints

    cfg = make_config(*TINY)
    env = make_env(cfg.env)
    full, history = trained(cfg, env, tmp_path / "full", "pods")

    real_save = Checkpoints.save

    def save_then_die(self, epoch, state, meta):
        real_save(self, epoch, state, meta)
        raise KeyboardInterrupt("killed after the first checkpoint")

    monkeypatch.setattr(Checkpoints, "save", save_then_die)
    with pytest.raises(KeyboardInterrupt):
        trained(cfg, env, tmp_path / "killed", "pods")
    monkeypatch.setattr(Checkpoints, "save", real_save)
    resumed, resumed_history = trained(cfg, env, tmp_path / "killed", "pods")

    for a, b in zip(jax.tree.leaves(full), jax.tree.leaves(resumed)):
        np.testing.assert_array_equal(a, b)
    assert resumed_history == history


# make test-slow: HDS through the command line end to end (80 s cold); make test keeps HDS's
# model inside the trainer (test_dynamics) and a saved HDS policy run through its model
# (test_api::test_hds_evaluate_runs_a_policy_through_a_learned_model)
@pytest.mark.slow
def test_hds_run_writes_every_output(tmp_path):
    out = tmp_path / "run"
    env = {**os.environ, "WANDB_MODE": "offline"}
    cmd = [
        sys.executable,
        "-m",
        "hds.run",
        *TINY[:-1],
        "method=hds",
        "real=brax",  # its oracle trains beside: two methods, two W&B runs
        # the model's data and fit at their smallest (the defaults fit for a minute), and the
        # model used however it fits: the trainer runs through it, as HDS does
        "dynamics.episodes=8",
        "dynamics.horizon=26",
        "dynamics.epochs=5",
        "dynamics.require_better=false",
        "seeds=2",
        f"hydra.run.dir={out}",
    ]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    methods = {(r["method"], r["seed"]) for r in summary["rows"]}
    assert methods == {("hds+mlp", 0), ("hds+mlp", 1), ("oracle", 0), ("oracle", 1)}
    for row in summary["rows"]:
        assert row["gap"] == pytest.approx(row["sim_return"] - row["real_return"])
    assert (out / "config.yaml").is_file()
    assert sorted(
        p.name for p in (out / "checkpoints" / "hds+mlp").iterdir() if p.name.isdigit()
    ) == [
        "3",
        "6",
    ]
    assert len(list((out / "wandb").glob("offline-run-*"))) == 2
    assert {p.name for p in (out / "plots").iterdir()} == {"learning_curves.png", "sim_vs_real.png"}
    assert "real_return" in proc.stdout and "Traceback" not in proc.stderr


# make test-slow (60 s cold): make test keeps a run on the corrected model
# (test_discover::test_command_line_writes_the_report_and_hds_run_accepts_the_corrected_model)
# and the simulator kinds' own tests (test_simulators)
@pytest.mark.slow
def test_the_corrected_and_the_real_simulator_close_the_gap(tmp_path):
    """simulator=corrected trains on the effects gap discovery names on plant data, and
    simulator=real (the oracle) on the plant's own: both then predict the plant's return far
    better than the nominal simulator does (20 N of Coulomb friction on the rail, C MuJoCo)."""
    from omegaconf import OmegaConf

    from hds.experiment import run, simulator_of

    small_data = ("dynamics.episodes=16", "dynamics.horizon=60", "discover.stride=2")
    gaps = {}
    for simulator in ("nominal", "corrected", "real"):
        cfg = make_config(*TINY, *small_data, f"simulator={simulator}", "seeds=2")
        result = run(cfg, tmp_path / simulator)
        OmegaConf.save(OmegaConf.structured(cfg), tmp_path / simulator / "config.yaml")
        gaps[simulator] = np.mean([abs(r["gap"]) for r in result.rows])
        if simulator == "corrected":
            assert {r["method"] for r in result.rows} == {"pods+corrected"}
            (found,) = result.discovery["effects"]
            assert (found["name"], found["target"]) == ("coulomb_friction", "slider")
            assert found["params"]["force"] == pytest.approx(20.0, rel=0.1)
            assert (tmp_path / simulator / "discovery" / "report.md").is_file()
            # the GIF of hds.report rebuilds this simulator from what the run wrote
            sites = simulator_of(cfg, tmp_path / simulator).env.sim.effects.sites
            assert [(e.name, e.target) for e in sites] == [("coulomb_friction", "slider")]
    assert gaps["corrected"] < 0.25 * gaps["nominal"], gaps
    assert gaps["real"] < 0.25 * gaps["nominal"], gaps
    # each exports the MJCF of the system it trained on, and policy.json says what that was
    import mujoco

    from hds.envs.system import resolve_xml
    from hds.policy import export_policy, load_policy

    contracts = {}
    for simulator in ("nominal", "corrected", "real"):
        policy = load_policy(tmp_path / simulator, seed=0)
        directory = export_policy(policy, tmp_path / "export" / simulator)
        contracts[simulator] = json.loads((directory / "policy.json").read_text())
        contracts[simulator]["xml"] = (directory / contracts[simulator]["mjcf"]).read_bytes()
    nominal, corrected, oracle = contracts.values()
    assert nominal["trained_on"]["simulator"] == "nominal" and not nominal["trained_on"]["effects"]
    assert nominal["xml"] == resolve_xml(make_config().env.xml).read_bytes()
    assert corrected["trained_on"]["simulator"] == "corrected"
    (effect,) = corrected["trained_on"]["effects"]
    assert (effect["name"], effect["params"]) == ("coulomb_friction", found["params"])
    assert corrected["mjcf"] == corrected["trained_on"]["mjcf"] == "cartpole_corrected.xml"
    model = mujoco.MjModel.from_xml_string(corrected["xml"].decode())
    assert model.dof_frictionloss[0] == pytest.approx(found["params"]["force"], rel=1e-5)
    assert oracle["trained_on"]["simulator"] == "oracle"
    assert [e["params"] for e in oracle["trained_on"]["effects"]] == [{"force": 20.0}]
    # the story of the three runs names discovery's friction beside the plant's 20 N
    from hds.report import sweep_story

    text, _ = sweep_story(tmp_path)
    (line,) = [x for x in text.splitlines() if x.startswith("  discovery named")]
    assert line.startswith("  discovery named coulomb_friction@slider force ")
    assert line.endswith("(plant: 20)")
    assert text.index("pods+corrected (2 seeds)") < text.index(line)


@pytest.mark.slow  # two rounds of recording and a discovery: ~1 min (make test-slow)
def test_the_corrected_simulator_excites_harder_until_the_data_can_identify(tmp_path):
    """80 N of rail friction: the gentle default excitation never moves the cart, so the
    corrected simulator records more at doubled amplitude, until the data move it, before
    discovery runs (which law it then names is the study's to judge)."""
    from hds.data import load
    from hds.discover import identifiability
    from hds.envs import make_env
    from hds.experiment import run_plants
    from hds.simulators import corrected_simulator

    cfg = make_config(
        *TINY, "dynamics.episodes=16", "dynamics.horizon=60", "discover.stride=2",
        "simulator=corrected", "real.friction_gap=4",
    )  # fmt: skip
    env, summary = corrected_simulator(cfg, make_env(cfg.env), run_plants(cfg)[0], tmp_path)
    assert summary["excitation_scale"] > cfg.dynamics.excitation_scale
    assert "slider moves in only" in summary["notes"][0]
    assert summary["episodes"] > cfg.dynamics.episodes
    data = load(tmp_path / "discovery" / "data.npz")
    assert data.n_episodes == summary["episodes"]
    rows = identifiability(data, cfg.env, cfg.discover.min_motion, cfg.discover.effects)
    assert all(r.identifiable or r.structural for r in rows)
    assert "coulomb_friction" in [e.name for e in env.sim.effects.sites]


def test_a_surrogate_friction_gradient_keeps_the_sharp_value():
    from hds.effects.friction import friction_direction

    v = jnp.linspace(-0.2, 0.2, 41)
    sharp = jax.vmap(jax.value_and_grad(lambda x: friction_direction(x, 50.0)))(v)
    surrogate = jax.vmap(jax.value_and_grad(lambda x: friction_direction(x, 50.0, 5.0)))(v)
    np.testing.assert_allclose(surrogate[0], sharp[0], atol=1e-6)  # the same law forward
    np.testing.assert_allclose(surrogate[1], 5.0 / jnp.cosh(5.0 * v) ** 2, rtol=1e-5)
    assert sharp[1][20] == pytest.approx(50.0) and surrogate[1][20] == pytest.approx(5.0)


def test_the_effect_ramp_grows_effects_from_nominal_to_their_values(cartpole_cfg):
    from hds.algo.continuation import effect_ramp

    effects = [
        {"name": "coulomb_friction", "target": "slider", "params": {"force": 20.0}},
        {"name": "actuator_gain", "target": "slide", "params": {"gain": 0.5}},
    ]
    env = make_env(cartpole_cfg, effects=effects)
    sites = env.sim.effects.sites
    at = lambda epoch, *ramp: effect_ramp(env.params, sites, epoch, *ramp)  # noqa: E731
    first, half, done = at(0, 0, 4), at(1, 0, 4), at(3, 0, 4)
    assert float(first[0]["force"]) == pytest.approx(5.0)  # a quarter of the way from 0
    assert float(first[1]["gain"]) == pytest.approx(0.875)  # ... and from 1 (nominal gain)
    assert float(half[0]["force"]) == pytest.approx(10.0)
    assert float(done[0]["force"]) == 20.0 and float(done[1]["gain"]) == 0.5
    late = [float(at(epoch, 10, 14)[0]["force"]) for epoch in (0, 9, 10, 13, 20)]
    assert late == pytest.approx([0.0, 0.0, 5.0, 20.0, 20.0])  # off until epoch 10
    assert at(0, 0, 0) is env.params  # no ramp: the values from the start


def _ramped_training(*overrides):
    """A tiny training whose effects grow in over epochs 2-4 of 10, one epoch per chunk: the
    trainer, its final state, the state at the start of each epoch, and the metrics."""
    cfg = make_config(
        *TINY, "algo.epochs=10", "algo.chunk=1", "anneal.effect_ramp=[0.2,0.4]", *overrides
    )
    trainer = make_train_from_config(cfg, make_env(cfg.env))
    run = jax.jit(trainer.run_chunk)
    state = trainer.init(jax.random.PRNGKey(0), trainer.default_hparams)
    states, chunks = [], []
    for _ in range(cfg.algo.epochs):
        states.append(state)
        state, metrics = run(state, trainer.default_hparams)
        chunks.append(metrics)
    metrics = {k: np.concatenate([np.asarray(m[k]) for m in chunks]) for k in chunks[0]}
    return trainer, state, states, metrics


# the continuation's waiting on its own, without training: tests/test_continuation.py
@pytest.mark.slow
def test_the_ramp_waits_for_the_policy_to_solve_the_task():
    """anneal.ramp_when_solved: a policy that solves the task from the first epoch meets the
    effects on the configured ramp (epochs 2-4) when one solved epoch is enough, one epoch
    later when it must solve 3 in a row (epochs 0-2: the ramp starts after epoch 2); one that
    never does, as late as the ramp can start and still end on the last epoch (7-9)."""
    *_, at_once = _ramped_training("env.task.solved_at=-1e9", "anneal.solved_for=1")
    *_, three = _ramped_training("env.task.solved_at=-1e9", "anneal.solved_for=3")
    *_, never = _ramped_training("env.task.solved_at=1e9")
    np.testing.assert_allclose(at_once["ramp"], [0, 0, 0.5, 1, 1, 1, 1, 1, 1, 1])
    np.testing.assert_allclose(three["ramp"], [0, 0, 0, 0.5, 1, 1, 1, 1, 1, 1])
    np.testing.assert_allclose(never["ramp"], [0, 0, 0, 0, 0, 0, 0, 0, 0.5, 1])


# the continuation's pausing on its own, without training: tests/test_continuation.py
@pytest.mark.slow
def test_a_pausing_ramp_stands_still_in_the_epochs_the_policy_fails():
    """anneal.ramp_pauses: once under way, the ramp advances after an epoch whose training
    return reaches env.task.solved_at and stands still after one that misses it, and still
    ends by the last epoch. The threshold is the return of the same training without pauses
    in the epoch before its ramp began: the ramp starts on time, and the returns on it, which
    go up and down, fall on both sides."""
    ramp = ("algo.epochs=16", "anneal.effect_ramp=[0.125,0.5]", "anneal.ramp_pauses=true")
    *_, free = _ramped_training(*ramp, "env.task.solved_at=-1e9")  # never pauses
    before = np.argmax(free["ramp"] > 0) - 1
    threshold = float(free["return"][before]) - 1e-3
    *_, paused = _ramped_training(*ramp, f"env.task.solved_at={threshold}")
    share, passed = paused["ramp"], paused["return"] >= threshold
    moving = (share[:-1] > 0) & (share[:-1] < 1)
    advanced = share[1:] > share[:-1]
    assert moving.any()
    np.testing.assert_array_equal(advanced[moving], passed[:-1][moving])
    assert (~passed[:-1][moving]).any() and passed[:-1][moving].any()  # both kinds happened
    assert share[-1] == 1.0


def test_keep_best_returns_the_best_policy_once_the_ramp_has_ended():
    trainer, state, states, metrics = _ramped_training(
        "env.task.solved_at=-1e9", "anneal.solved_for=1", "algo.keep=best"
    )
    done = np.nonzero(metrics["ramp"] >= 1)[0]
    best = done[np.argmax(metrics["return"][done])]
    kept, last = trainer.final_policy(state), state.policy  # last: after the final update
    for a, b in zip(jax.tree.leaves(kept), jax.tree.leaves(states[best].policy), strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(jax.tree.leaves(kept)[0], jax.tree.leaves(last)[0])
