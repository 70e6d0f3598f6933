"""The sim2real gap: a trained policy's return on the simulator and on the "real" plant, from
the same initial states. gap = sim return - real return (positive: the policy does worse on the
real system than the simulator promised)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hds.algo.rollout import policy_rollout
from hds.data import initial_states
from hds.real import rollout
from hds.results import Row
from hds.utils.runtime import CompiledPrograms, program_key


class MeanCI(NamedTuple):
    """A mean and its 95% interval; a tuple, so `mean, low, high = ...` unpacks it."""

    mean: float
    low: float
    high: float

    def __str__(self) -> str:
        return f"{self.mean:.4g} [{self.low:.4g}, {self.high:.4g}]"


def mean_ci(values) -> MeanCI:
    """Mean and 95% Student-t interval (the interval is the mean alone for one value)."""
    values = np.asarray(values, dtype=float)
    mean = float(values.mean())
    if len(values) < 2:
        return MeanCI(mean, mean, mean)
    # scipy.stats here, not at the top: importing it costs every `python -m hds.run` ~1 s
    # (2-core AMD EPYC), and a run that reports no interval never needs it
    from scipy import stats

    half = float(stats.t.ppf(0.975, len(values) - 1) * stats.sem(values))
    return MeanCI(mean, mean - half, mean + half)


class Evaluator:
    """Compiled once per run: deterministic policy on the simulator (batched over the runs of
    the batch and episodes) and on the plant (a host loop with a jitted policy). `plant` is one
    plant, or one per run of the batch (a swept friction gap)."""

    def __init__(self, env, policy, plant, episodes: int = 32, seed: int = 12345):
        self.env, self.policy, self.plant = env, policy, plant
        task, sim = env.task, env.sim
        self.q0, self.qd0 = initial_states(task, seed, episodes)
        q0, qd0 = jnp.asarray(self.q0), jnp.asarray(self.qd0)
        low, high = jnp.asarray(sim.ctrl_range[:, 0]), jnp.asarray(sim.ctrl_range[:, 1])

        def sim_returns(params, effects):
            act = lambda o: policy.apply(params, o)  # noqa: E731

            def one(q, qd):
                _, _, r = policy_rollout(
                    env,
                    effects,
                    task,
                    act,
                    env.sim.init(q, qd, effects),
                    jax.random.PRNGKey(0),
                    0.0,
                    task.horizon,
                    low,
                    high,
                )
                return r.sum()

            return jax.vmap(one)(q0, qd0)

        self._batched = jax.vmap(sim_returns)  # over the batch of runs
        # the program cache's key of the evaluation (its closure: the env, the policy, the
        # initial states): a later process of the configuration deserializes the program
        # instead of tracing the rollout (hds.utils.runtime.cached_lowering)
        self._key = program_key("evaluation", sim_returns)
        self._programs = CompiledPrograms(self._key)  # by the arguments' shapes
        self._act = jax.jit(policy.apply)

    def sim_returns(self, params, effects=None) -> np.ndarray:
        """[n_runs, episodes]; `effects`: each run's effect parameters, stacked (default: the
        env's own for every run)."""
        if effects is None:
            n_runs = jax.tree.leaves(params)[0].shape[0]
            effects = jax.tree.map(lambda x: jnp.stack([x] * n_runs), self.env.params)
        return np.asarray(self._programs("sim_returns", self._batched, params, effects))

    def real_returns(self, params, plant=None) -> np.ndarray:
        """[n_runs, episodes] on the evaluation's plant(s), or on `plant` (one, or one per run)."""
        n_runs = jax.tree.leaves(params)[0].shape[0]
        plant = self.plant if plant is None else plant
        plants = plant if isinstance(plant, list) else [plant] * n_runs
        return np.stack(
            [
                # one run's parameters sliced in numpy (jax compiled a slice per leaf's shape)
                self.episodes(
                    jax.tree.map(lambda x, s=s: np.asarray(x)[s], params), plants[s]
                ).returns
                for s in range(n_runs)
            ]
        )

    def episodes(self, params, plant):
        """The episodes (hds.real.Episodes) of one run's policy (`params`, unbatched) on
        `plant` from the evaluation's initial states."""
        task = self.env.task
        act = lambda obs: np.asarray(self._act(params, jnp.asarray(obs, jnp.float32)))  # noqa: E731
        return rollout(plant, task, self.q0, self.qd0, act, task.horizon)


def gap_rows(
    method: str, runs: list[dict], sim: np.ndarray, real: np.ndarray, solved_at=None
) -> list[Row]:
    """One row per run of the batch (`runs`: its seed and swept settings), mean over episodes;
    with the task's `solved_at` (env.task), whether the policy solves it on the simulator
    and on the plant."""
    rows = []
    for s, run in enumerate(runs):
        sim_r, real_r = float(np.mean(sim[s])), float(np.mean(real[s]))
        solved = {}
        if solved_at is not None:
            solved = {"solved_sim": sim_r >= solved_at, "solved_real": real_r >= solved_at}
        rows.append(Row.measured(method, sim_r, real_r, settings=dict(run), **solved))
    return rows


def diverged(
    method: str, runs: list[dict], sim: np.ndarray, real: np.ndarray, train_returns=None
) -> list[str]:
    """A line for each run of the batch some of whose evaluation rollouts diverged (NaN or inf
    returns), saying how many of them, on the simulator and on the plant, and whether its
    training rollouts diverged in every epoch (`train_returns`: per run, each epoch's mean)."""
    lines = []
    for s, run in enumerate(runs):
        counts = {
            where: (int((~np.isfinite(r[s])).sum()), r[s].size)
            for where, r in (("simulator", sim), ("plant", real))
        }
        bad = [f"{n} of {total} on the {where}" for where, (n, total) in counts.items() if n]
        if bad:
            every = " (every rollout)" if all(n == t for n, t in counts.values()) else ""
            label = ", ".join(f"{k}={v}" for k, v in run.items())
            trained = ""
            if train_returns is not None and not np.isfinite(train_returns[s]).any():
                trained = (
                    "; its training rollouts diverged in every epoch too, and were all skipped "
                    "as non-finite: the policy never learned"
                )
            lines.append(
                f"{method} {label}: evaluation rollouts diverged to NaN or inf{every}: "
                f"{' and '.join(bad)}{trained}; lower env.timestep, check env.effects and "
                "real.effects for huge values, or lower algo.step_size"
            )
    return lines


def no_finite_result(rows: list[Row] | list[dict]) -> str | None:
    """The message of a run none of whose rows is finite (it exits non-zero), else None."""
    returns = [  # Rows, or as JSON (None: a NaN read back from a finished run's summary.json)
        (r.sim_return, r.real_return) if isinstance(r, Row) else (r["sim_return"], r["real_return"])
        for r in rows
    ]
    finite = [all(v is not None and np.isfinite(v) for v in pair) for pair in returns]
    if rows and not any(finite):
        return (
            f"no finite result: every row ({len(rows)}) has a NaN or inf return (see the "
            "warnings above); summary.json writes them as null and lists them under non_finite"
        )
    return None
