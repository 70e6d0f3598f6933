"""`python -m hds.evaluate run=<run dir> [method=...] [seed=...] [real=...] [eval_episodes=N]`:
evaluate a saved policy on any plant (another friction, another effect) and on the simulator
it trained on, from the same initial states. Writes evaluation.json, plots/trajectories.png
and sim_vs_real.gif into out= (default: <run dir>/evaluations/<plant>).

    python -m hds.evaluate run=outputs/runs/x/t real.friction_gap=2 eval_episodes=64
    python -m hds.evaluate run=outputs/runs/x/t real=brax \
        'real.effects=[{name: actuator_gain, target: slide, params: {gain: 0.8}}]'

The `real` overrides compose as they do for `python -m hds.run`; without them the run's own
plant is used. (In Python: `hds.evaluate_policy(policy, real=...)`, hds/policy.py.)

`model=<dir>`, a learned dynamics model (an HDS run's <run dir>/dynamics), adds what HDS's
rollouts through it meet: the policy's return run through the model from the same initial
states, and the model's k-step errors along the policy's episodes on the plant, next to the
simulator's and constant velocity's (evaluation.json's "model"):

    python -m hds.evaluate run=outputs/runs/x/t model=outputs/runs/x/t/dynamics
"""

from __future__ import annotations

import os
import re
from pathlib import Path

os.environ.setdefault("WANDB_MODE", "offline")

from hds.config import SEED_MAX, SWEEP_KEYS
from hds.utils import cli  # noqa: E402

KEYS = {
    "run": Path,
    "method": str,
    "seed": int,
    **dict.fromkeys(SWEEP_KEYS, float),
    "eval_episodes": int,
    "eval_seed": int,
}
KEYS |= {"out": Path, "gif": cli.boolean, "model": Path}


def main(argv: list[str]) -> Path:
    args, real_overrides = cli.parse(argv, KEYS, "hds.evaluate", passthrough=("real",))
    if args.get("eval_episodes", 1) < 1:
        raise ValueError(
            f"eval_episodes = {args['eval_episodes']} evaluates nothing: give at least 1, or "
            "leave it out for the run's own count"
        )
    if not 0 <= args.get("eval_seed", 0) <= SEED_MAX:
        raise ValueError(f"eval_seed = {args['eval_seed']} must lie in [0, {SEED_MAX}]")
    setting = {k: args.pop(k) for k in SWEEP_KEYS if k in args}
    from hds.config import compose
    from hds.policy import evaluate_policy, load_policy
    from hds.utils.runtime import enable_compilation_cache

    real = compose(real_overrides).real if real_overrides else None  # validated, before loading
    enable_compilation_cache()
    policy = load_policy(args["run"], args.get("method"), args.get("seed"), **setting)
    name = re.sub(r"[^\w.=,-]+", "_", ",".join(real_overrides)) or "default"
    out = args.get("out") or args["run"] / "evaluations" / name
    episodes, seed = args.get("eval_episodes"), args.get("eval_seed")
    real_eval = evaluate_policy(policy, real, episodes, seed)
    extra = {}
    if args.get("model"):
        extra["model"] = through_model(policy, args["model"], real_eval)
    return write_evaluation(
        policy, real_eval, out, episodes, seed, gif=args.get("gif", True), extra=extra
    )


def through_model(policy, model_dir: Path, real_eval) -> dict:
    """The policy run through the learned model at `model_dir` from the initial states of its
    episodes on the plant (`real_eval`), and the model's k-step errors along those episodes
    (hds.dynamics.evaluate: model, constant velocity, simulator); printed and returned."""
    from hds import dynamics
    from hds.gap import mean_ci

    env = policy.simulator
    model = dynamics.load(model_dir, env)
    obs, actions = real_eval.episodes.obs, real_eval.episodes.actions
    returns = dynamics.closed_loop_returns(
        model, env.task, policy, obs[:, 0], actions.shape[1], env.sim.ctrl_range
    )
    errors = dynamics.evaluate(model, obs, actions, policy.config.dynamics.eval_steps, env)
    (mean, lo, hi), (real_mean, *_) = mean_ci(returns), real_eval.mean_ci()
    print(
        f"through the model: return {mean:.4g} [{lo:.4g}, {hi:.4g}] (worst episode "
        f"{returns.min():.4g}); on the plant {real_mean:.4g} (worst {real_eval.returns.min():.4g})"
    )
    print(
        "open-loop nrmse along the policy's episodes on the plant (model / constant velocity / "
        f"simulator): {dynamics.describe_errors(errors)}"
    )
    return {
        "path": str(model_dir),
        "returns": returns.tolist(),
        "mean": mean,
        "ci95": [lo, hi],
        "k_step": errors,
    }


def write_evaluation(
    policy, real_eval, out: Path, episodes, seed, gif: bool = True, extra: dict | None = None
) -> Path:
    """evaluation.json (returns on the plant and on the simulator the policy trained on, from
    the same initial states, and `extra`'s entries), plots/trajectories.png and, with gif,
    sim_vs_real.gif."""
    from hds import plots
    from hds.animate import animate
    from hds.config import run_label
    from hds.gap import mean_ci
    from hds.policy import evaluate_policy
    from hds.utils.io import atomic_write_json

    sim_eval = evaluate_policy(policy, episodes=episodes, seed=seed, plant=policy.training_plant())
    names, dt = policy.obs_names, policy.dt
    sim_obs, real_obs = sim_eval.episodes.obs[0], real_eval.episodes.obs[0]
    titles = (
        f"simulator: return {sim_eval.returns[0]:.4g}",
        f"plant: return {real_eval.returns[0]:.4g}",
    )
    plots.save(plots.trajectories(sim_obs, real_obs, names, dt), out / "plots" / "trajectories.png")
    if gif:
        animate(sim_obs, real_obs, names, dt, out / "sim_vs_real.gif", titles, policy.env.xml)
    sim_ci, real_ci = sim_eval.mean_ci(), real_eval.mean_ci()
    # the episodes start from the same states: the gap's interval is over their differences
    gap_ci = mean_ci(sim_eval.returns - real_eval.returns)
    summary = {
        "run_dir": str(policy.run_dir),
        "method": policy.method,
        "run": policy.run,
        "epoch": policy.epoch,
        "real": real_eval.to_json(),
        "sim": sim_eval.to_json(),
        "gap": sim_ci.mean - real_ci.mean,
        "gap_ci95": [gap_ci.low, gap_ci.high],
        **(extra or {}),
    }
    atomic_write_json(out / "evaluation.json", summary)
    plant = real_eval.plant
    effects = ", ".join(
        f"{e['name']}@{e['target']} {fmt_params(e['params'])}" for e in plant.get("effects", [])
    )
    where = f"{plant.get('plant')} plant" + (f" ({effects})" if effects else "")
    n = len(real_eval.returns)
    print(f"{policy.method} {run_label(policy.run)}, {n} episodes, mean [95% interval]:")
    print(f"  return on the {where}: {real_ci}")
    print(f"  return on the simulator it trained on: {sim_ci}")
    print(f"  sim2real gap (simulator - plant): {gap_ci}")
    return out


def fmt_params(params: dict) -> str:
    return "{" + ", ".join(f"{k}: {v:g}" for k, v in params.items()) + "}"


if __name__ == "__main__":
    print(f"wrote {cli.run(main)}")
