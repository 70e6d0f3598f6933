"""Section `reference`: the reference project's configuration, end to end, per backend and
line-search length, against the reference implementation's 573 s (FIELD-NOTES.md).

One training = build the env and trainer, trace and compile `jax.jit(trainer.train)` (the whole
run as one program), run it. Total wall time counts all of that (the reference's 573 s counted
its compiles too). The trained policy is then evaluated deterministically from 50 fixed initial
states (PRNGKey(1), 100 steps each) on its own backend and on brax generalized, next to the
zero-action return from the same states.
"""

from __future__ import annotations

import jax
import numpy as np

from bench.common import (
    REFERENCE,
    REFERENCE_IMPL,
    FixedStates,
    block,
    compose,
    steps_per_epoch,
    summary,
    timed,
)

DEFAULT_BUDGET = {
    # the closed-form cart-pole engine, the generic tree engine (any contact-free MJCF), brax's
    "backends": ["analytic", "tree", "generalized"],
    "line_search": [4, 8],
    "seeds": 3,  # seeds trained per setting on hds's own engines (seed 0 is the timed one)
    "slow_seeds": 1,  # ... on brax backends, where one training takes minutes
    "hds_backends": ["analytic"],  # HDS with the reference's HDS settings, for comparison
    "eval_episodes": 50,
    "eval_seed": 1,
    "cross_check": "generalized",  # every policy is also evaluated on this backend
    "speedup_target": 20.0,
    # config overrides for every training, e.g. a user's own MJCF of the cart-pole:
    # env.xml=bench/assets/cartpole_renamed.xml,real=none (its joints renamed: the default
    # plant's friction names the cart-pole's `slider`)
    "overrides": [],
}
FAST = ("analytic", "tree")  # hds's own engines: a training takes seconds
# The reference project's HDS settings (FIELD-NOTES.md): alpha 2e-3, noise 0.1 halving per epoch.
HDS_OVERRIDES = ("method=hds", "algo.step_size=2e-3", "noise.scale=0.1", "noise.decay=0.5")


class Evaluations:
    """FixedStates evaluators per backend of the reference task, built once each."""

    def __init__(self, episodes: int, seed: int, cross_check: str | None = "generalized"):
        self.episodes, self.seed, self.cross_check = episodes, seed, cross_check
        self._by_backend: dict[str, FixedStates] = {}

    def of(self, backend: str) -> FixedStates:
        if backend not in self._by_backend:
            from hds.envs import make_env

            env = make_env(compose(*REFERENCE, f"env.backend={backend}").env)
            self._by_backend[backend] = FixedStates(env, self.episodes, self.seed)
        return self._by_backend[backend]

    def built(self) -> list[str]:
        return sorted(self._by_backend)


def train_timed(cfg) -> dict:
    """Build, trace, compile and run one training; returns timings, the compiled program and
    the trained state of seed `cfg.seed`."""
    from hds.algo.pods import make_train_from_config
    from hds.envs import make_env

    with timed() as build:
        env = make_env(cfg.env)
        trainer = make_train_from_config(cfg, env)
    key, hparams = jax.random.PRNGKey(cfg.seed), trainer.default_hparams
    with timed() as trace:
        lowered = jax.jit(trainer.train).lower(key, hparams)
    with timed() as comp:
        compiled = lowered.compile()
    with timed() as run:
        state, metrics = block(compiled(key, hparams))
    return {
        "build_s": build.s,
        "trace_s": trace.s,
        "compile_s": comp.s,
        "run_s": run.s,
        "compiled": compiled,
        "hparams": hparams,
        "state": state,
        "metrics": metrics,
        "trainer": trainer,
    }


def measure(
    label: str, overrides: tuple[str, ...], backend: str, seeds: int, evals: Evaluations
) -> dict:
    """One setting: the timed training of seed 0, `seeds - 1` more seeds through the same
    compiled program (untimed), and the evaluation of every trained policy."""
    cfg = compose(*overrides, f"env.backend={backend}")
    t = train_timed(cfg)
    epochs = cfg.algo.epochs
    steps = steps_per_epoch(cfg)
    apply = t["trainer"].policy.apply
    policies = [t["state"].policy]
    for s in range(1, seeds):
        state, _ = block(t["compiled"](jax.random.PRNGKey(cfg.seed + s), t["hparams"]))
        policies.append(state.policy)
    own = [float(np.mean(evals.of(backend).returns(apply, p))) for p in policies]
    check = evals.cross_check
    on_generalized = (
        [float(np.mean(evals.of(check).returns(apply, p))) for p in policies]
        if check and check != backend
        else None
    )
    total = t["build_s"] + t["trace_s"] + t["compile_s"] + t["run_s"]
    return {
        "label": label,
        "backend": backend,
        "line_search": steps["candidates"],
        "build_s": t["build_s"],
        "trace_s": t["trace_s"],
        "compile_s": t["compile_s"],
        "run_s": t["run_s"],
        "epoch_s": t["run_s"] / epochs,
        "total_s": total,
        "reference_s": REFERENCE_IMPL[f"{label}_train_s"],
        "speedup_vs_reference": REFERENCE_IMPL[f"{label}_train_s"] / total,
        "simulated_steps_per_s": steps["simulated"] * epochs / t["run_s"],
        "samples_per_s": steps["samples"] * epochs / t["run_s"],
        "steps_per_epoch": steps,
        "final_return_seed0": own[0],
        "final_return": summary(own),
        "final_return_on_generalized": summary(on_generalized) if on_generalized else None,
        "train_return_curve": [float(x) for x in np.asarray(t["metrics"]["return"])],
    }


def run(budget: dict) -> dict:
    evals = Evaluations(budget["eval_episodes"], budget["eval_seed"], budget["cross_check"])
    runs = []

    def seeds_on(backend):
        return budget["seeds"] if backend in FAST else budget["slow_seeds"]

    for backend in budget["backends"]:
        for n in budget["line_search"]:
            runs.append(
                measure(
                    "pods",
                    (*REFERENCE, f"algo.line_search={n}", *budget["overrides"]),
                    backend,
                    seeds_on(backend),
                    evals,
                )
            )
    for backend in budget["hds_backends"]:
        overrides = (*REFERENCE, *HDS_OVERRIDES, *budget["overrides"])
        runs.append(measure("hds", overrides, backend, seeds_on(backend), evals))
    zero = {b: summary(evals.of(b).zero_action()) for b in evals.built()}
    return present(runs, zero, budget)


def present(runs: list[dict], zero: dict, budget: dict) -> dict:
    target_s = REFERENCE_IMPL["pods_train_s"] / budget["speedup_target"]
    ref_return = REFERENCE_IMPL["pods_final_return"]
    rows = [
        [
            r["label"],
            r["backend"],
            r["line_search"],
            r["compile_s"] + r["trace_s"],
            r["epoch_s"],
            r["total_s"],
            f"{r['speedup_vs_reference']:.1f}x of {r['reference_s']:.0f} s",
            r["simulated_steps_per_s"],
            r["final_return_seed0"],
            f"{r['final_return']['mean']:.0f} [{r['final_return']['min']:.0f}, "
            f"{r['final_return']['max']:.0f}] (n={r['final_return']['n']})",
            r["final_return_on_generalized"]["mean"] if r["final_return_on_generalized"] else None,
        ]
        for r in runs
    ]
    targets = []
    for r in runs:
        if r["label"] != "pods":
            continue
        ok_time = r["total_s"] <= target_s
        ok_return = r["final_return"]["min"] >= ref_return
        targets.append(
            {
                "target": f"{r['backend']}, line_search={r['line_search']}: "
                f"total <= {target_s:.1f} s "
                f"({budget['speedup_target']:.0f}x less than 573 s) at final return >= "
                f"{ref_return:,.0f}",
                "value": f"{r['total_s']:.1f} s ({r['speedup_vs_reference']:.1f}x), worst seed "
                f"{r['final_return']['min']:,.0f}",
                "met": ok_time and ok_return,
            }
        )
    return {
        "title": "the reference configuration, end to end",
        "tables": [
            {
                "caption": "Training (seed 0 timed; compile = trace + XLA compile of the whole "
                "training; total = env build + compile + run; steps/s = all simulated "
                "env steps, line search included)",
                "columns": [
                    "method",
                    "backend",
                    "line search",
                    "compile s",
                    "epoch s",
                    "total s",
                    "speed-up vs reference",
                    "sim steps/s",
                    "return seed 0",
                    "return mean [min, max] over seeds",
                    f"same policies on {budget['cross_check']}",
                ],
                "rows": rows,
            },
            {
                "caption": "Baselines on the same 50 fixed initial states",
                "columns": ["policy", "backend", "mean return", "min", "max"],
                "rows": [["zero action", b, z["mean"], z["min"], z["max"]] for b, z in zero.items()]
                + [
                    [
                        "reference PODS (its own states)",
                        "brax generalized (reference code)",
                        REFERENCE_IMPL["pods_final_return"],
                        None,
                        None,
                    ],
                    [
                        "reference zero action (its own states)",
                        "brax generalized (reference code)",
                        REFERENCE_IMPL["zero_action_return"],
                        None,
                        None,
                    ],
                ],
            },
        ],
        "targets": targets,
        "notes": [
            "Returns: mean total reward of the deterministic policy over 50 rollouts of 100 "
            "steps from fixed initial states drawn with PRNGKey(1) from the task's distribution "
            "(q, qd uniform in [-5, 5]), reward -cos^2(theta) - theta_dot^2 - 1.5 x^2 - "
            "0.5 x_dot^2 (env=cartpole_reference). The reference's -12,858 was measured on its "
            "own 50 states from the same distribution: same task definition, different draws.",
            f"Reference implementation (573 s, -12,858): {REFERENCE_IMPL['source']}.",
            "HDS row: method=hds with the reference's HDS settings (alpha 2e-3, noise 0.1 "
            "halving every epoch, simulated annealing), no learned model (dynamics=none); the "
            "reference HDS took 779 s and scored -990.",
            "Extra seeds reuse the compiled program; only seed 0 is timed.",
        ],
        "data": {"runs": runs, "zero_action": zero, "reference_impl": REFERENCE_IMPL},
    }
