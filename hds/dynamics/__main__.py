"""`python -m hds.dynamics [--out DIR] [--policy RUN_DIR] [overrides...]`: fit the configured
dynamics model on data from the configured plant and print its open-loop errors on fresh
held-out episodes, next to constant velocity and the simulator alone. Overrides are Hydra's, as
for `python -m hds.run`:

  python -m hds.dynamics dynamics=residual real=brax
  python -m hds.dynamics dynamics=ensemble dynamics.episodes=128 --out models/ensemble

`--policy RUN_DIR` holds out episodes of that run's trained policy deployed on the plant
instead of excitation (the states and controls HDS's rollouts meet), and prints the policy's
return through the model next to its return on the plant, from the same initial states.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        prog="python -m hds.dynamics", description=__doc__.split("\n")[0]
    )
    parser.add_argument("--out", help="save the fitted model to this directory")
    parser.add_argument(
        "--test-episodes",
        type=int,
        default=16,
        help="held-out episodes, recorded with another seed (default 16)",
    )
    parser.add_argument(
        "--policy",
        help="held out: this run directory's trained policy deployed on the plant, not excitation",
    )
    parser.add_argument("--seed", type=int, help="with --policy: the run's seed (default: first)")
    parser.add_argument("--json", help="write the report and held-out errors to this file")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. dynamics=residual")
    args = parser.parse_args(argv)

    import jax

    from hds import dynamics
    from hds.config import compose
    from hds.envs import make_env
    from hds.real import make_plant
    from hds.utils.runtime import enable_compilation_cache

    try:
        cfg = compose(args.overrides)  # unknown keys and range errors: one line
    except ValueError as err:
        sys.exit(f"error: {err}")
    enable_compilation_cache()
    dcfg = cfg.dynamics if cfg.dynamics.model != "none" else replace(cfg.dynamics, model="mlp")
    env = make_env(cfg.env)
    plant = make_plant(cfg.real, cfg.env)
    key = jax.random.PRNGKey(cfg.seed)
    k_train, k_test, k_fit = jax.random.split(key, 3)

    policy = None
    if args.policy:
        from hds.policy import load_policy

        try:
            policy = load_policy(args.policy, seed=args.seed)
        except (FileNotFoundError, ValueError) as err:
            sys.exit(f"error: {err}")
        if policy.env.name != cfg.env.name:
            sys.exit(
                f"error: the policy of {args.policy} was trained for env {policy.env.name}, "
                f"this model is of {cfg.env.name}; give env={policy.env.name}"
            )
    start = time.perf_counter()
    train = dynamics.collect_data(dcfg, env, plant, k_train)
    if policy is None:
        test = dynamics.collect_data(replace(dcfg, episodes=args.test_episodes), env, plant, k_test)
    else:
        test = deployed(policy, env, plant, k_test, args.test_episodes, dcfg.horizon)
    collect_s = time.perf_counter() - start
    model, report = dynamics.fit(dcfg, env, train, key=k_fit)
    held_out = dynamics.evaluate(model, test.obs, test.actions, dcfg.eval_steps, env)
    if args.out:
        report["path"] = str(dynamics.save(args.out, model, dcfg, report))

    print(
        f"{dcfg.model} ({report['members']} member(s), hidden {report['hidden']}) on "
        f"{cfg.real.plant} plant data: {report['transitions']['train']} training transitions, "
        f"collected in {collect_s:.1f} s, fitted in {report['fit_s']:.1f} s "
        f"({report['epochs_run']} epochs, best {report['best_epoch']})"
    )
    what = (
        "excitation"
        if policy is None
        else f"the policy of {args.policy} (seed {policy.run['seed']})"
    )
    print(f"open-loop nrmse on {args.test_episodes} held-out episodes of {what} (lower is better):")
    print(f"{'k':>4} {'model':>9} {'const-vel':>10} {'simulator':>10}")
    for k, row in held_out.items():
        print(
            f"{k:>4} "
            + " ".join(
                f"{_fmt(row[n]):>{w}}"
                for n, w in (("model", 9), ("baseline", 10), ("simulator", 10))
            )
        )
    result = {"report": report, "held_out": held_out, "overrides": args.overrides}
    if policy is not None:
        result["returns"] = closed_loop_returns(policy, model, env, test)
        (model_mean, model_worst), (plant_mean, plant_worst) = (
            result["returns"][k] for k in ("model", "plant")
        )
        print(
            f"the policy's return through the model {model_mean:.4g} (worst episode "
            f"{model_worst:.4g}), on the plant {plant_mean:.4g} (worst {plant_worst:.4g})"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return result


def deployed(policy, env, plant, key, episodes: int, horizon: int):
    """A Dataset of `policy` run on `plant` from `episodes` of the task's initial states."""
    from hds.data import collect, initial_states

    q0, qd0 = initial_states(env.task, key, episodes)
    return collect(plant, env.task, q0, qd0, policy, horizon)


def closed_loop_returns(policy, model, env, data) -> dict:
    """The policy's return, mean and worst episode, run through `model` from the initial states
    of `data` (its episodes on the plant), and on the plant (the same task's rewards)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from hds.algo.rollout import perturbed_rollout

    task, nq = env.task, model.nq
    low, high = (jnp.asarray(env.sim.ctrl_range[:, i], jnp.float32) for i in (0, 1))
    zeros = jnp.zeros(data.actions.shape[1:], jnp.float32)
    act = lambda o: policy(o)  # noqa: E731 (a JAX array in, a JAX array out)
    through_model = jax.jit(
        jax.vmap(lambda s: perturbed_rollout(model, None, task, act, s, zeros, low, high)[2])
    )(jnp.asarray(data.obs[:, 0], jnp.float32)).sum(1)
    after = jnp.asarray(data.obs[:, 1:], jnp.float32)
    rewards = jax.vmap(jax.vmap(task.reward))(after[..., :nq], after[..., nq:], data.actions)
    on_plant = rewards.sum(1)
    return {
        name: [float(np.mean(r)), float(np.min(r))]
        for name, r in (("model", through_model), ("plant", on_plant))
    }


def _fmt(x) -> str:
    return "nan" if x is None else f"{x:.4f}"


if __name__ == "__main__":
    main()
