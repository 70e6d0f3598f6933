"""A balancing reference for the balance tasks' thresholds: a discrete LQR on the tree engine's
dynamics linearised at upright (the task's own state weights, effort weight as R), its mean
and worst return on bench.peers' 50 fixed initial states.

  python -m bench.survey_systems.lqr_check double_cartpole_balance
"""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from bench.common import FixedStates
from bench.peers import task_env
from bench.peers_systems import DEFAULT_BUDGET


def lqr_gain(env, task) -> np.ndarray:
    nq = len(task.q_mean)

    def step(x, u):
        state = env.step(env.sim.init(x[:nq], x[nq:], env.params), u, env.params)
        return jnp.concatenate(env.qqd(state))

    x0, u0 = jnp.zeros(2 * nq), jnp.zeros(env.sim.n_act)
    a = np.asarray(jax.jacfwd(step, 0)(x0, u0))
    b = np.asarray(jax.jacfwd(step, 1)(x0, u0))
    q = np.diag([*task.q_weight, *task.qd_weight])
    r = np.eye(env.sim.n_act) * task.effort
    p = scipy.linalg.solve_discrete_are(a, b, q, r)
    return np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)


def main(name: str) -> None:
    cfg, env = task_env(name, DEFAULT_BUDGET)
    gain = jnp.asarray(lqr_gain(env, cfg.env.task))
    returns = FixedStates(env).returns(lambda _, obs: -(gain @ obs), None)  # obs = [q, qd]
    print(
        f"{name}: LQR mean {returns.mean():.1f}, median {np.median(returns):.1f}, "
        f"worst {returns.min():.1f}, second worst {np.sort(returns)[1]:.1f}"
    )


if __name__ == "__main__":
    main(sys.argv[1])
