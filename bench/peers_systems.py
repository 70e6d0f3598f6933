"""Section `peers_systems`: section `peers` (bench/peers.py) on the tree engine's systems
(docs/systems.md), with the same reward, horizon and initial states for every method. By default the
issue's row: closed-loop PODS with the swing-up settings against brax's PPO on the double
cart-pole swing-up, 5 seeds, medians of the wall clock and samples to the task's threshold.
Its own section, so its rows stand beside the cart-pole's in bench/results.json. Thresholds
are each task's env.task.solved_at (conf/env/*.yaml).

The survey of the other tasks (one seed; experiments/systems/README.md quotes it), e.g.
  python -m bench.run peers_systems --out DIR --set peers_systems.seeds=0 \\
    --set peers_systems.tasks=double_cartpole_balance,furuta_balance \\
    --set peers_systems.methods=pods_cl,hds,ppo
and the Furuta balance, which closed-loop PODS with a horizon curriculum solves
(bench/survey_systems/furuta_balance/):
  python -m bench.run peers_systems --out DIR --set peers_systems.tasks=furuta_balance \\
    --set peers_systems.methods=pods_cl_horizon,ppo --set peers_systems.pods_epochs=100
"""

from __future__ import annotations

from bench.peers import DEFAULT_BUDGET as CARTPOLE
from bench.peers import run  # noqa: F401  (bench.run calls this section's run)

DEFAULT_BUDGET = {
    **CARTPOLE,
    "tasks": ["double_cartpole_swingup"],
    "backend": "tree",
    # no real plant: the default one hides friction on a joint named `slider` (docs/systems.md)
    "overrides": ["real=none"],
    "methods": ["pods_cl_swingup", "ppo"],
    "thresholds": {},
    "pods_epochs": 60,  # conf/experiment/swingup.yaml's
    "seeds": [0, 1, 2, 3, 4],
    "ppo_timesteps": {
        "double_cartpole_swingup": 600_000,
        "double_cartpole_balance": 300_000,
        "furuta_swingup": 600_000,
        "furuta_balance": 300_000,
        "acrobot_swingup": 600_000,
    },
}
