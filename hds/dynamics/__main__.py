"""`python -m hds.dynamics [out=DIR] [test_episodes=N] [json=FILE] [overrides...]`: fit the
configured dynamics model on data from the configured plant and print its open-loop errors on
fresh held-out episodes, next to constant velocity and the simulator alone. The overrides are
Hydra's, as for `python -m hds.run`:

  python -m hds.dynamics dynamics=residual real=brax
  python -m hds.dynamics dynamics=ensemble dynamics.episodes=128 out=models/ensemble

out: save the fitted model to this directory; test_episodes: held-out episodes, recorded with
another seed (default 16); json: write the report and held-out errors to this file.
"""

from __future__ import annotations

import os
import time
from dataclasses import replace
from pathlib import Path

from hds.utils import cli

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")

KEYS = {"out": Path, "test_episodes": int, "json": Path}  # the rest: the config's overrides


def main(argv: list[str]) -> dict:
    own = [a for a in argv if a.partition("=")[0] in KEYS or a in ("-h", "--help")]
    overrides = [a for a in argv if a not in own]
    args, _ = cli.parse(own, KEYS, "hds.dynamics", required=())
    test_episodes = args.get("test_episodes", 16)
    if test_episodes < 1:
        raise ValueError(f"test_episodes = {test_episodes} must be at least 1")

    import jax

    from hds import dynamics
    from hds.config import compose
    from hds.data.budget import check_planned
    from hds.envs import make_env
    from hds.real import make_plant
    from hds.utils.io import atomic_write_json
    from hds.utils.runtime import enable_compilation_cache

    cfg = compose(overrides)  # unknown keys and range errors: one line (cli.run)
    enable_compilation_cache()
    dcfg = cfg.dynamics if cfg.dynamics.model != "none" else replace(cfg.dynamics, model="mlp")
    # it records dynamics.episodes on the plant (dynamics.data is not read here) and fits on them
    check_planned(replace(cfg, dynamics=replace(dcfg, data=None)), fit=True)
    env = make_env(cfg.env)
    plant = make_plant(cfg.real, cfg.env)
    key = jax.random.PRNGKey(cfg.seed)
    k_train, k_test, k_fit = jax.random.split(key, 3)

    start = time.perf_counter()
    train = dynamics.collect_data(dcfg, env, plant, k_train)
    test = dynamics.collect_data(replace(dcfg, episodes=test_episodes), env, plant, k_test)
    collect_s = time.perf_counter() - start
    model, report = dynamics.fit(dcfg, env, train, key=k_fit)
    held_out = dynamics.evaluate(model, test.obs, test.actions, dcfg.eval_steps, env)
    if args.get("out"):
        report["path"] = str(dynamics.save(args.get("out"), model, dcfg, report))

    print(
        f"{dcfg.model} ({report['members']} member(s), hidden {report['hidden']}) on "
        f"{cfg.real.plant} plant data: {report['transitions']['train']} training transitions, "
        f"collected in {collect_s:.1f} s, fitted in {report['fit_s']:.1f} s "
        f"({report['epochs_run']} epochs, best {report['best_epoch']})"
    )
    print(f"open-loop nrmse on {test_episodes} held-out episodes (lower is better):")
    print(f"{'k':>4} {'model':>9} {'const-vel':>10} {'simulator':>10}")
    for k, row in held_out.items():
        print(
            f"{k:>4} "
            + " ".join(
                f"{_fmt(row[n]):>{w}}"
                for n, w in (("model", 9), ("baseline", 10), ("simulator", 10))
            )
        )
    result = {"report": report, "held_out": held_out, "overrides": overrides}
    if args.get("json"):
        atomic_write_json(args["json"], result)
    return result


def _fmt(x) -> str:
    return "nan" if x is None else f"{x:.4f}"


if __name__ == "__main__":
    cli.run(main)
