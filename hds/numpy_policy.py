"""An hds policy exported by `python -m hds.export`, run with NumPy alone (no JAX, no hds).

    import numpy_policy
    policy = numpy_policy.load("exported/")   # the directory with policy.json and policy.npz
    u = policy(obs)                           # obs [..., n_obs] -> u [..., n_act]

policy.json names the observations, actions and control range; this file must stay
self-contained: it is copied next to every export.
"""

import json
from pathlib import Path

import numpy as np


def load(directory):
    directory = Path(directory)
    spec = json.loads((directory / "policy.json").read_text())
    weights = np.load(directory / "policy.npz")
    layers = [(weights[layer["kernel"]], weights[layer["bias"]]) for layer in spec["layers"]]
    hinge = np.asarray(spec["hinge_angles"], dtype=bool)
    low, high = np.asarray(spec["control_range"], dtype=np.float32).T
    mid, half = (high + low) / 2, (high - low) / 2

    def policy(obs):
        obs = np.asarray(obs, dtype=np.float32)
        q, rest = obs[..., : len(hinge)], obs[..., len(hinge) :]
        angles = q[..., hinge]
        x = np.concatenate([q[..., ~hinge], np.sin(angles), np.cos(angles), rest], axis=-1)
        for kernel, bias in layers[:-1]:
            x = np.tanh(x @ kernel + bias)
        kernel, bias = layers[-1]
        return mid + half * np.tanh(x @ kernel + bias)

    policy.spec = spec
    return policy
