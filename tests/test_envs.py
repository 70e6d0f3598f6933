"""The differentiable simulator: finite rollouts of the right shape, gradients that agree with
finite differences, tasks that reward what they say."""

from __future__ import annotations

import os
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hds.config import EffectConfig
from hds.envs import make_env
from tests.conftest import make_config

T = 25


def rollout_return(env, params, state, actions):
    def step(s, u):
        s = env.step(s, u, params)
        return s, (env.observe(s, params), env.task.reward(*env.qqd(s), u))

    _, (obs, rewards) = jax.lax.scan(step, state, actions)
    return rewards.sum(), obs


@pytest.fixture(scope="module")
def friction_env():
    """The cart-pole simulator carrying smoothed Coulomb friction and damping effects (on the
    closed-form backend the studies train on: the effects act alike on every backend, and it
    compiles in seconds where brax's generalized backend takes most of a minute)."""
    cfg = make_config(
        "env.backend=analytic",
        "env.effects=[{name: coulomb_friction, target: slider, params: {force: 10}},"
        "{name: viscous_damping, target: hinge, params: {coefficient: 0.1}}]",
    ).env
    return make_env(cfg)


@pytest.fixture(scope="module")
def batch(cartpole_env):
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    # one compiled program: brax's reset run eagerly compiles each of its ops on its own
    # (~200 small programs, twice the CPU time)
    states = jax.jit(jax.vmap(cartpole_env.reset))(keys)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (8, T, 1), minval=-1, maxval=1)
    return states, actions


def test_rollouts_are_finite_with_the_right_shapes(cartpole_env, batch):
    states, actions = batch
    run = jax.jit(jax.vmap(lambda s, a: rollout_return(cartpole_env, cartpole_env.params, s, a)))
    returns, obs = run(states, actions)
    assert returns.shape == (8,) and obs.shape == (8, T, 4)
    assert np.all(np.isfinite(obs)) and np.all(np.isfinite(returns))
    assert cartpole_env.sim.dt == pytest.approx(0.04)


def test_gradient_of_return_matches_finite_differences(friction_env):
    """Directional derivatives of the return w.r.t. the actions, through smoothed friction."""
    state = friction_env.reset(jax.random.PRNGKey(3))
    actions = 0.5 * jax.random.normal(jax.random.PRNGKey(4), (T, 1))

    def ret(a):
        return rollout_return(friction_env, friction_env.params, state, a)[0]

    # one compiled program (the generalized backend compiles slowly): its value is the return
    value_and_grad = jax.jit(jax.value_and_grad(ret))
    _, grad = value_and_grad(actions)
    value = lambda a: value_and_grad(a)[0]  # noqa: E731
    for seed in range(3):
        direction = jax.random.normal(jax.random.PRNGKey(10 + seed), actions.shape)
        direction /= jnp.linalg.norm(direction)
        eps = 1e-2
        fd = (value(actions + eps * direction) - value(actions - eps * direction)) / (2 * eps)
        analytic = jnp.vdot(grad, direction)
        assert float(analytic) == pytest.approx(float(fd), rel=0.03, abs=1e-3)
    # the last action moves the last state, whose reward counts: its gradient is not zero
    assert float(jnp.abs(grad[-1]).sum()) > 0


def test_reward_prefers_upright(cartpole_env):
    task = cartpole_env.task
    zero = jnp.zeros(1)
    upright = task.reward(jnp.zeros(2), jnp.zeros(2), zero)
    hanging = task.reward(jnp.array([0.0, np.pi]), jnp.zeros(2), zero)
    tilted = task.reward(jnp.array([0.0, 0.3]), jnp.zeros(2), zero)
    assert upright == 0.0 and hanging < tilted < upright


def test_reference_task_is_the_reference_projects():
    env = make_env(make_config("env=cartpole_reference").env)
    task = env.task
    assert env.sim.dt == pytest.approx(0.04) and task.horizon == 100
    q, qd = task.initial(jax.random.PRNGKey(0))
    assert np.all(np.abs(q) <= 5) and np.all(np.abs(qd) <= 5)
    # its quirk, kept in this variant only: horizontal (theta = pi/2) scores best
    r = lambda th: float(task.reward(jnp.array([0.0, th]), jnp.zeros(2), jnp.zeros(1)))  # noqa: E731
    assert r(np.pi / 2) > r(0.0)
    assert r(0.0) == pytest.approx(-1.0)


def test_task_vector_sizes_are_checked():
    cfg = make_config("env=pendulum_swingup", "real=none", "env.task.q_weight=[1,2]").env
    with pytest.raises(ValueError, match="env.task.q_weight has 2 entries, and this model needs 1"):
        make_env(cfg)


def test_effect_on_unknown_target_names_the_allowed_ones(cartpole_cfg):
    wheel = "[{name: coulomb_friction, target: wheel, params: {force: 1}}]"
    message = r"no joint 'wheel'; choose one of \['slider', 'hinge'\]"
    with pytest.raises(ValueError, match="env.effects: effect 'coulomb_friction' .*" + message):
        make_config(f"env.effects={wheel}")  # at validation, before anything compiles
    with pytest.raises(ValueError, match="real.effects: effect 'coulomb_friction' .*" + message):
        make_config(f"real.effects={wheel}", "real=brax")
    # the builders run the same check on configs that never went through validate()
    effect = EffectConfig("coulomb_friction", "wheel", {"force": 1.0})
    with pytest.raises(ValueError, match=message):
        make_env(replace(cartpole_cfg, effects=[effect]))


def test_missing_mjcf_is_a_clear_error(cartpole_cfg):
    with pytest.raises(ValueError, match="env.xml: MJCF '/nowhere/robot.xml' not found"):
        make_config("env.xml=/nowhere/robot.xml")
    with pytest.raises(FileNotFoundError, match="MJCF '/nowhere/robot.xml' not found"):
        make_env(replace(cartpole_cfg, xml="/nowhere/robot.xml"))


def _ten_steps(env) -> np.ndarray:
    """Observations of 10 steps (0.4 s) of a constant push from a tilted, moving start (the
    start computed in the same program: run eagerly, brax compiles each of its ops apart)."""

    def ten_steps(params):
        state = env.sim.init(jnp.array([0.1, 0.2]), jnp.array([0.0, 0.3]), params)

        def step(s, _):
            s = env.step(s, jnp.array([0.5]), params)
            return s, env.observe(s, params)

        return jax.lax.scan(step, state, None, length=10)[1]

    return np.asarray(jax.jit(ten_steps)(env.params))


# Largest difference from brax's generalized backend over those 10 steps, per observation
# (q_slider m, q_hinge rad, qd_slider m/s, qd_hinge rad/s). mjx solves the same equations
# (measured ~2e-7); spring and positional are brax's approximate pipelines (measured: 0.015 m,
# 0.19 rad, 0.08 m/s, 1.15 rad/s), whose integrators differ.
TOLERANCE = {
    "mjx": [1e-5, 1e-5, 1e-5, 1e-5],
    "spring": [0.03, 0.3, 0.15, 2.0],
    "positional": [0.03, 0.3, 0.15, 2.0],
}


# mjx compiles for over a minute on 2 cores: make test-slow
@pytest.mark.parametrize(
    "backend", ["spring", "positional", pytest.param("mjx", marks=pytest.mark.slow)]
)
def test_other_backends_track_the_generalized_one(backend, cartpole_env):
    env = make_env(make_config(f"env.backend={backend}").env)
    obs, reference = _ten_steps(env), _ten_steps(cartpole_env)
    assert np.all(np.abs(obs - reference).max(0) <= TOLERANCE[backend]), obs - reference
    assert np.abs(reference[-1] - reference[0]).max() > 0.5  # the states did move


def test_every_effect_at_its_nominal_value_is_a_no_op(batch):
    """Gap discovery fits candidates as a superset of effects at their nominal values: each must
    then leave the dynamics exactly as they are."""
    from hds.effects import LIBRARY

    sample = {"joint": "slider", "actuator": "slide", "body": "pole", "observation": "q_hinge"}
    effects = [
        {"name": n, "target": sample[e.target_kind], "params": {}} for n, e in LIBRARY.items()
    ]
    cfg = make_config("env.backend=analytic").env  # effects act alike on every backend
    loaded, plain = make_env(cfg, effects=effects), make_env(cfg)
    _, actions = batch
    keys = jax.random.split(jax.random.PRNGKey(0), actions.shape[0])

    def run(env):
        return jax.jit(jax.vmap(lambda k, a: rollout_return(env, env.params, env.reset(k), a)))(
            keys, actions
        )[1]

    np.testing.assert_array_equal(run(loaded), run(plain))


def test_a_brax_backend_s_env_prints_nothing_on_its_first_import():
    """brax imports mujoco.mjx, which prints `Failed to import warp` where warp is absent:
    a fresh process that builds a generalized env and steps it keeps its stdout clean."""
    import subprocess
    import sys

    script = (
        "import jax; from hds.envs import make_env;"
        "from hds.config.composition import compose;"
        "env = make_env(compose(['env.backend=generalized']).env);"
        "state = env.sim.init(env.sim.sys.init_q, jax.numpy.zeros(env.sim.sys.qd_size()));"
        "print('built', env.sim.backend)"
    )
    run = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "HDS_PROGRAM_CACHE": "off"},
    )
    assert run.stdout.strip() == "built generalized", run.stdout
