"""Step 1, compare: replay the measured actions in the simulator from the measured states and
measure how far its predictions land, one step and k steps ahead, per state variable."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hds.discover.data import Data
from hds.discover.fit import Engine


@dataclass
class Errors:
    """Prediction errors of one model on one set of episodes."""

    one_step_rmse: np.ndarray  # [n_obs] measurement units
    rollout_rmse: np.ndarray  # [n_obs] over every step of every k-step window
    normalized: float  # RMSE of k-step errors, each variable in units of its std

    def to_json(self, names) -> dict:
        return {
            "one_step_rmse": [float(x) for x in self.one_step_rmse],
            "rollout_rmse": [float(x) for x in self.rollout_rmse],
            "rollout_nrmse": float(self.normalized),
            "names": list(names),
        }


@dataclass
class Residuals:
    """Measured minus predicted, for the windows of one set (padding dropped)."""

    one_step: np.ndarray  # [W, n_obs] after the first step of each window
    rollout: np.ndarray  # [W, k, n_obs]
    predicted: np.ndarray  # [W, k, n_obs]
    episode: np.ndarray  # [W] stacked-episode index
    start: np.ndarray  # [W]


def residuals(engine: Engine, data: Data, set_name: str, theta, delay) -> Residuals:
    """Prediction residuals of theta (with its delays) on a set, hinge angles wrapped."""
    arrays = data.arrays(set_name)
    windows = data.windows[set_name]
    keep = windows.mask > 0
    pred = engine.predictions(theta, delay, arrays)[keep]
    obs = np.asarray(data.obs, dtype=np.float64)
    episode, start = windows.episode[keep], windows.start[keep]
    idx = start[:, None] + 1 + np.arange(data.horizon)[None, :]
    measured = obs[episode[:, None], idx]
    err = measured - pred
    sim = engine.model.sim
    angular = np.zeros(sim.n_obs, dtype=bool)
    angular[: sim.nq] = sim.angular
    err[..., angular] = np.angle(np.exp(1j * err[..., angular]))
    return Residuals(err[:, 0], err, pred, episode, start)


def errors(res: Residuals, scale) -> Errors:
    scale = np.asarray(scale, dtype=np.float64)
    rollout = np.sqrt(np.mean(res.rollout**2, axis=(0, 1)))
    return Errors(
        one_step_rmse=np.sqrt(np.mean(res.one_step**2, axis=0)),
        rollout_rmse=rollout,
        normalized=float(np.sqrt(np.mean((rollout / scale) ** 2))),
    )


def compare(engine: Engine, data: Data, theta, delay) -> dict[str, tuple[Residuals, Errors]]:
    """Residuals and errors of one model on every set of the data."""
    out = {}
    for name in data.windows:
        res = residuals(engine, data, name, theta, delay)
        out[name] = (res, errors(res, data.scale))
    return out
