"""Tasks: where episodes start and what they reward. Rewards are smooth in state and action.

Termination: a rollout always runs the full horizon, and nothing resets in the middle. A task
that would "fail" (pole fallen, cart far away) just keeps paying its cost, so the return stays
a smooth function of the actions. The return counts the reward of every state reached, the
last one included: R = sum_{t=0}^{T-1} r(s_{t+1}, a_t).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np


@dataclass(frozen=True, eq=False)
class Task:
    kind: str  # "target" (quadratic cost to a target state) or "reference"
    horizon: int
    q_mean: np.ndarray
    q_spread: np.ndarray  # initial q uniform in q_mean +- q_spread
    qd_spread: np.ndarray  # initial qd uniform in +- qd_spread
    q_target: np.ndarray
    q_weight: np.ndarray
    qd_weight: np.ndarray
    effort: float
    angular: np.ndarray  # bool per q entry: hinge joints, whose error wraps around
    # [nq, nq] to the angles the cost reads (`env.task.angles=world`: each link's angle in the
    # world); None: the joints' own
    angle_map: np.ndarray | None = None

    def initial(self, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        kq, kqd = jax.random.split(key)
        q = self.q_mean + self.q_spread * jax.random.uniform(
            kq, self.q_mean.shape, minval=-1, maxval=1
        )
        qd = self.qd_spread * jax.random.uniform(kqd, self.qd_spread.shape, minval=-1, maxval=1)
        return q, qd

    def reward(self, q: jax.Array, qd: jax.Array, u: jax.Array) -> jax.Array:
        """Reward of reaching (q, qd) after applying control u."""
        if self.kind == "reference":
            return reference_reward(q, qd)
        err = q - self.q_target
        if self.angle_map is not None:
            err = self.angle_map @ err
        # 2 (1 - cos e) equals e^2 near the target and is periodic for hinges.
        q_cost = jnp.where(self.angular, 2.0 * (1.0 - jnp.cos(err)), err**2)
        return -(
            jnp.dot(self.q_weight, q_cost)
            + jnp.dot(self.qd_weight, qd**2)
            + self.effort * jnp.sum(u**2)
        )


def reference_reward(q, qd):
    """The reference project's per-step reward, kept as it was (its quirk included: -cos^2 is
    best with the pole horizontal, not upright). Cart-pole only: q = [x, theta]."""
    x, theta = q[0], q[1]
    x_dot, theta_dot = qd[0], qd[1]
    return -(jnp.cos(theta) ** 2) - theta_dot**2 - 1.5 * x**2 - 0.5 * x_dot**2


def make_task(cfg, angular: np.ndarray, nq: int, nv: int, link_angles: np.ndarray) -> Task:
    """Build a task from `env.task` config, checking every vector against the model's size.
    `link_angles` ([nq, nq], `system.link_angles`) is what `angles=world` costs."""
    sizes = {
        "q_mean": nq,
        "q_spread": nq,
        "qd_spread": nv,
        "q_target": nq,
        "q_weight": nq,
        "qd_weight": nv,
    }
    vectors = {}
    for name, size in sizes.items():
        value = np.asarray(getattr(cfg, name), dtype=np.float32)
        if value.shape != (size,):
            raise ValueError(
                f"env.task.{name} has {value.size} entries, and this model needs {size} "
                f"(one per {'q' if name.startswith('q_') else 'qd'} entry)"
            )
        vectors[name] = value
    if cfg.kind == "reference" and (nq, nv) != (2, 2):
        raise ValueError("env.task.kind=reference is the cart-pole's task: it needs nq = nv = 2")
    return Task(
        kind=cfg.kind,
        horizon=int(cfg.horizon),
        effort=float(cfg.effort),
        angular=angular,
        angle_map=np.asarray(link_angles, np.float32) if cfg.angles == "world" else None,
        **vectors,
    )
