"""Section `peers_systems`: section `peers` (bench/peers.py) on the tree engine's systems (README,
"Systems"): brax's PPO against closed-loop PODS and HDS on the double cart-pole, Furuta and
acrobot tasks, with the same reward, horizon and initial states. Its own section, so its rows
stand beside the cart-pole's in bench/results.json. Thresholds are each task's
env.task.solved_at (conf/env/*.yaml).
"""

from __future__ import annotations

from bench.peers import DEFAULT_BUDGET as CARTPOLE
from bench.peers import run  # noqa: F401  (bench.run calls this section's run)

DEFAULT_BUDGET = {
    **CARTPOLE,
    "tasks": [
        "double_cartpole_swingup",
        "double_cartpole_balance",
        "furuta_swingup",
        "furuta_balance",
        "acrobot_swingup",
    ],
    "backend": "tree",
    # no real plant: the default one hides friction on a joint named `slider` (README, "Systems")
    "overrides": ["real=none"],
    "methods": ["pods_cl", "pods_cl_swingup", "hds", "ppo"],
    "thresholds": {},
    "ppo_timesteps": {
        "double_cartpole_swingup": 600_000,
        "double_cartpole_balance": 300_000,
        "furuta_swingup": 600_000,
        "furuta_balance": 300_000,
        "acrobot_swingup": 600_000,
    },
}
