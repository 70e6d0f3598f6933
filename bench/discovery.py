"""Section `discovery`: time to a gap-discovery report on 20 episodes x 200 steps of measured
data. Skipped, with a note, where the module `hds.discover` does not exist.

Data: the "real" plant of the default config (C MuJoCo with a hidden 20 N Coulomb friction on
the slider, conf/real/mujoco.yaml) driven by random force steps (held 0.1 to 0.5 s, 15 % of the
actuator range) from random states with the pole anywhere. Then `hds.discover.discover` on the
default simulator (env=cartpole_balance) on each backend of the budget, and `write_report`
into a temporary directory: the time a user waits for report.md after having the data.

Each row fits on its own backend (`discover.backend` set to it: the default, auto, would fit on
the analytic backend whatever the env's), and starts with discovery's engine cache and JAX's
in-memory caches emptied, so each row pays its own compiles.
"""

from __future__ import annotations

import dataclasses
import tempfile

import numpy as np

from bench.common import compose, timed

DEFAULT_BUDGET = {
    "episodes": 20,
    "steps": 200,
    "seed": 0,
    "stride": 1,  # DiscoverConfig's default: a k-step window starts at every step
    # generalized (the default env's backend) takes about 11 minutes here: add it with
    # --set discovery.backends=analytic,generalized
    "backends": ["analytic"],
}


def record(plant, task, episodes: int, steps: int, seed: int):
    from hds.data.collect import collect
    from hds.data.excitation import random_steps

    rng = np.random.default_rng(seed)
    q0 = np.c_[rng.uniform(-0.5, 0.5, episodes), rng.uniform(-np.pi, np.pi, episodes)]
    qd0 = rng.uniform(-0.5, 0.5, (episodes, 2))
    u = random_steps(
        seed + 1,
        episodes,
        steps,
        plant.dt,
        plant.ctrl_range,
        min_hold=0.1,
        max_hold=0.5,
        scale=0.15,
    )
    return collect(plant, task, q0, qd0, u)


def run(budget: dict) -> dict:
    title = "time to a gap-discovery report"
    runs = [measure(backend, budget) for backend in budget["backends"]]
    stages = sorted({k for r in runs for k in r["timing"]})
    return {
        "title": title,
        "tables": [
            {
                "caption": f"Seconds ({budget['episodes']} episodes x {budget['steps']} steps "
                f"from the {runs[0]['plant']} plant; simulator env={runs[0]['env']} on each "
                "backend; discover()'s stages from Result.timing)",
                "columns": [
                    "backend",
                    "env + plant build",
                    "data collection",
                    "discover()",
                    *[f"of which {k}" for k in stages],
                    "write_report()",
                    "data to report",
                ],
                "rows": [
                    [
                        r["backend"],
                        r["build_s"],
                        r["collect_s"],
                        r["discover_s"],
                        *[r["timing"].get(k) for k in stages],
                        r["report_s"],
                        r["collect_s"] + r["discover_s"] + r["report_s"],
                    ]
                    for r in runs
                ],
            }
        ],
        "notes": [
            f"{r['backend']}: hidden in the plant: {r['hidden']}; named by discovery: "
            + ("; ".join(r["named"]) if r["named"] else "nothing")
            + f" (stopped: {r['stopped']})."
            for r in runs
        ]
        + [
            "Compile time is included in every row: no persistent cache, and discovery's "
            "engine cache and JAX's in-memory caches are emptied before each row (the rows "
            "share one process, so only its start-up, imports and JAX's initialisation, falls "
            "on the first row)."
        ],
        "data": runs,
    }


def discover_config(cfg, backend: str, stride: int):
    """Discovery's settings for one row: the config's, fitted on `backend` itself."""
    return dataclasses.replace(cfg.discover, backend=backend, stride=stride)


def forget_compiled() -> None:
    """Empty discovery's engine cache and JAX's in-memory caches, so the next row compiles
    its own programs instead of reusing an earlier row's."""
    import jax

    from hds.discover import fit

    fit._ENGINES.clear()
    jax.clear_caches()


def measure(backend: str, budget: dict) -> dict:
    from hds.discover import discover, write_report
    from hds.envs import make_env
    from hds.real import make_plant

    cfg = compose(f"env.backend={backend}")
    forget_compiled()
    with timed() as build:
        env = make_env(cfg.env)
        plant = make_plant(cfg.real, cfg.env)
    with timed() as data_t:
        dataset = record(plant, env.task, budget["episodes"], budget["steps"], budget["seed"])
    with timed() as found:
        result = discover(dataset, cfg.env, discover_config(cfg, backend, budget["stride"]))
    if result.backend != backend:  # the row is labelled by the backend the fits ran on
        raise RuntimeError(f"discovery fitted on {result.backend}, not on {backend}")
    with tempfile.TemporaryDirectory(prefix="hds-bench-report-") as out, timed() as written:
        write_report(result, cfg.env, out)
    named = [
        f"{e.name} on {e.target}: "
        + ", ".join(f"{k} {v:.3g} {e.units.get(k, '')}".strip() for k, v in e.params.items())
        for e in result.missing_effects
    ]
    return {
        "backend": result.backend,
        "plant": cfg.real.plant,
        "env": cfg.env.name,
        "hidden": ", ".join(f"{e.name} on {e.target} {dict(e.params)}" for e in cfg.real.effects),
        "build_s": build.s,
        "collect_s": data_t.s,
        "discover_s": found.s,
        "report_s": written.s,
        "timing": dict(result.timing),
        "named": named,
        "stopped": result.stopped,
    }
