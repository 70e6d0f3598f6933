"""Action improvement on a small linear system, where everything can be checked exactly: the
line search never accepts a worse sequence, and the Gauss-Newton step equals a direct solve."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hds.algo.improve import ImproveSettings, gauss_newton_matrix, gauss_newton_step, improve
from hds.algo.rollout import open_loop_return
from hds.envs.tasks import Task

DT, T = 0.1, 8


class DoubleIntegrator:
    """x'' = u: an engine (reset/step/observe/qqd) with linear dynamics."""

    def reset(self, key):
        return jax.random.uniform(key, (2,), minval=-1, maxval=1)

    def step(self, state, u, params):
        q, qd = state
        qd = qd + DT * u[0]
        return jnp.array([q + DT * qd, qd])

    def observe(self, state, params):
        return state

    def qqd(self, state):
        return state[:1], state[1:]


TASK = Task(
    kind="target",
    horizon=T,
    q_mean=np.zeros(1, np.float32),
    q_spread=np.ones(1, np.float32),
    qd_spread=np.ones(1, np.float32),
    q_target=np.zeros(1, np.float32),
    q_weight=np.ones(1, np.float32),
    qd_weight=np.full(1, 0.1, np.float32),
    effort=0.01,
    angular=np.zeros(1, bool),
)
ENGINE = DoubleIntegrator()


def settings(order="first", anneal="line_search", candidates=6):
    return ImproveSettings(
        order=order, grad_clip=1e6, gn_damping=1e-6, candidates=candidates, anneal=anneal
    )


def improve_batch(alpha, cfg, n=16):
    states = jax.vmap(ENGINE.reset)(jax.random.split(jax.random.PRNGKey(0), n))
    actions = jax.random.normal(jax.random.PRNGKey(1), (n, T, 1))
    run = jax.jit(
        jax.vmap(
            lambda s, a, k: improve(
                ENGINE,
                None,
                TASK,
                s,
                a,
                k,
                alpha=alpha,
                temperature=0.0,
                cfg=cfg,
                low=-10.0,
                high=10.0,
            )
        )
    )
    return states, actions, run(states, actions, jax.random.split(jax.random.PRNGKey(2), n))


@pytest.mark.parametrize("alpha", [1e-3, 0.1, 1e3])
def test_line_search_never_accepts_a_worse_sequence(alpha):
    states, actions, out = improve_batch(alpha, settings())
    recomputed = jax.vmap(lambda s, a: open_loop_return(ENGINE, None, TASK, s, a))(
        states, out.actions
    )
    assert np.all(np.asarray(recomputed) >= np.asarray(out.value) - 1e-5)
    np.testing.assert_allclose(recomputed, out.new_value, rtol=1e-5, atol=1e-5)
    rejected = ~np.asarray(out.accepted)
    np.testing.assert_array_equal(np.asarray(out.actions)[rejected], np.asarray(actions)[rejected])
    if alpha == 1e-3:  # a small gradient step always improves a smooth return
        assert np.all(np.asarray(out.accepted))


def test_a_huge_fixed_step_is_taken_and_a_huge_line_search_step_is_not():
    _, _, fixed = improve_batch(1e4, settings(anneal="fixed", candidates=1))
    _, _, searched = improve_batch(1e4, settings(candidates=1))
    assert np.all(np.asarray(fixed.accepted)) and np.all(fixed.new_value < fixed.value)
    assert not np.any(np.asarray(searched.accepted))


def test_gauss_newton_step_matches_a_direct_solve():
    """Linear dynamics and a quadratic cost: the Gauss-Newton matrix is the exact Hessian of the
    cost, so its damped step must equal numpy's solve with the autodiff Hessian."""
    state = jnp.array([0.5, -0.3])
    actions = jax.random.normal(jax.random.PRNGKey(5), (T, 1))
    cost = lambda a: -open_loop_return(ENGINE, None, TASK, state, a.reshape(T, 1))  # noqa: E731
    # each in one compiled program (run eagerly, every op of the rollout compiles on its own)
    H = jax.jit(lambda a: gauss_newton_matrix(ENGINE, None, TASK, state, a))(actions)
    exact = jax.jit(jax.hessian(cost))(actions.reshape(-1))
    np.testing.assert_allclose(H, exact, rtol=1e-4, atol=1e-6)
    g = -jax.jit(jax.grad(cost))(actions.reshape(-1))
    damping = 1e-2
    step = gauss_newton_step(H, g, damping)
    lam = damping * np.mean(np.diag(exact)) + 1e-6
    direct = np.linalg.solve(
        np.asarray(exact, np.float64) + lam * np.eye(T), np.asarray(g, np.float64)
    )
    np.testing.assert_allclose(step, direct, rtol=1e-3, atol=1e-6)
    # and on a quadratic problem the undamped step lands (almost) on the optimum
    _, _, out = improve_batch(1.0, settings(order="second"), n=4)
    assert np.all(np.asarray(out.accepted))


def test_second_order_improves_more_than_first_order_in_one_step():
    _, _, first = improve_batch(0.05, settings())
    _, _, second = improve_batch(1.0, settings(order="second"))
    assert np.mean(second.new_value - second.value) > np.mean(first.new_value - first.value)


def test_a_nan_gradient_skips_the_sample():
    state = jnp.array([0.5, -0.3])
    actions = jnp.zeros((T, 1)).at[3, 0].set(jnp.nan)
    out = improve(
        ENGINE,
        None,
        TASK,
        state,
        actions,
        jax.random.PRNGKey(0),
        alpha=0.1,
        temperature=0.0,
        cfg=settings(),
        low=-10.0,
        high=10.0,
    )
    assert bool(out.skipped) and not bool(out.accepted)


def test_windowed_gradient_is_the_full_one_over_the_horizon_and_myopic_over_one_step():
    """algo.grad_window (closed loop, SHAC-style truncation): values never change; a window
    of the whole horizon gives the full gradient; a window of one step leaves each
    perturbation only its own step's reward, d r(f(s_t, u_t), u_t) / d delta_t at fixed s_t."""
    from hds.algo.rollout import perturbed_rollout

    act = lambda o: jnp.array([-2.0 * o[0] - 0.5 * o[1]])  # noqa: E731  a linear feedback
    state = jnp.array([0.5, -0.3])
    deltas = jax.random.normal(jax.random.PRNGKey(6), (T, 1))
    low, high = jnp.full(1, -10.0), jnp.full(1, 10.0)

    def ret(d, window):
        return perturbed_rollout(ENGINE, None, TASK, act, state, d, low, high, window)[2].sum()

    full = jax.grad(ret)(deltas, 0)
    np.testing.assert_allclose(jax.grad(ret)(deltas, T), full, rtol=1e-6)
    for window in (1, 3):
        np.testing.assert_allclose(ret(deltas, window), ret(deltas, 0), rtol=1e-6)
    # s_t before each step: the rollout's observations (this engine observes its state)
    states = perturbed_rollout(ENGINE, None, TASK, act, state, deltas, low, high)[0]

    def own_reward(s, d):
        u = act(s) + d
        return TASK.reward(*ENGINE.qqd(ENGINE.step(s, u, None)), u)

    own = jax.vmap(jax.grad(own_reward, 1))(states, deltas)
    np.testing.assert_allclose(jax.grad(ret)(deltas, 1), own, rtol=1e-5, atol=1e-7)
    assert not np.allclose(own, full)


@pytest.mark.parametrize(
    "closed_loop, order", [(False, "first"), (False, "second"), (True, "first")]
)
def test_an_improvement_horizon_counts_only_its_first_steps(closed_loop, order):
    """anneal.horizon_start's curriculum: with `horizon` h, the improvement maximises the
    rewards of the first h steps; the actions after step h move nothing it counts, so they
    keep their values, and the return it reports is the first h steps' (open loop, first and
    second order, and closed loop)."""
    from hds.algo.rollout import perturbed_rollout, trajectory

    h = 3
    state = jnp.array([0.8, -0.2])
    actions = jax.random.normal(jax.random.PRNGKey(7), (T, 1))
    low, high = jnp.full(1, -10.0), jnp.full(1, 10.0)
    act = (lambda o: jnp.array([-2.0 * o[0] - 0.5 * o[1]])) if closed_loop else None  # noqa: E731

    def run(counted):
        return improve(
            ENGINE,
            None,
            TASK,
            state,
            actions,
            jax.random.PRNGKey(0),
            alpha=0.5,
            temperature=0.0,
            cfg=settings(order),
            low=low,
            high=high,
            act=act,
            counted=counted,
        )

    out = run((jnp.arange(T) < h).astype(jnp.float32))
    rewards = (
        perturbed_rollout(ENGINE, None, TASK, act, state, actions, low, high)[2]
        if closed_loop
        else trajectory(ENGINE, None, TASK, state, actions)[1]
    )
    assert bool(out.accepted)
    np.testing.assert_allclose(out.value, rewards[:h].sum(), rtol=1e-6)
    np.testing.assert_array_equal(out.actions[h:], actions[h:])
    assert not np.allclose(out.actions[:h], actions[:h])
    whole = run(None)  # no mask: every step counts, the last actions move too
    np.testing.assert_allclose(whole.value, rewards.sum(), rtol=1e-6)
    assert not np.allclose(whole.actions[h:], actions[h:])


def test_the_improvement_horizon_grows_from_its_start_to_the_whole_horizon():
    from hds.algo.continuation import counted_steps

    masks = [counted_steps(jnp.int32(e), 10, 20.0, 100) for e in (0, 10, 20, 30)]
    assert [int(m.sum()) for m in masks] == [10, 55, 100, 100]
    for m in masks:  # the first steps, in one block
        assert np.all(np.asarray(m)[: int(m.sum())] == 1)
    assert counted_steps(jnp.int32(5), 0, 20.0, 100) is None  # off: no mask at all
    assert counted_steps(jnp.int32(5), 100, 20.0, 100) is None  # a start of the whole horizon
