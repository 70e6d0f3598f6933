"""Step 2, locate: where the simulator and the data disagree.

For every state variable, the size of its one-step residual; and for every candidate feature
(each joint's position or angle, velocity, speed and velocity sign; each action; the time
since the action last changed), how much of that residual the feature accounts for: the
correlation ratio eta^2 = between-bin variance / total variance of the residual, with the
feature cut into quantile bins (or its few values). eta^2 sees any dependence, linear or not:
a step at zero velocity (dry friction), a slope (viscous friction, gain), a plateau (dead
zone). A feature's score weighs its eta^2 by its variable's share of the total residual, so
the most telling pair is a large residual that one feature explains.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hds.discover.compare import Residuals
from hds.discover.data import Data


@dataclass
class Location:
    variables: list[str]
    share: np.ndarray  # [n_obs] each variable's share of the normalized one-step residual
    table: list[dict]  # {variable, feature, eta2, score}, best first
    features: dict[str, np.ndarray]  # feature name -> [W] values
    residual: np.ndarray  # [W, n_obs] one-step residuals

    @property
    def top(self) -> dict | None:
        return self.table[0] if self.table else None


def time_since_change(actions: np.ndarray) -> np.ndarray:
    """[E, T] steps since each episode's action last changed (any actuator)."""
    changed = np.zeros(actions.shape[:2], dtype=bool)
    changed[:, 1:] = np.any(np.abs(np.diff(actions, axis=1)) > 1e-9, axis=-1)
    out = np.zeros(actions.shape[:2])
    for t in range(1, actions.shape[1]):
        out[:, t] = np.where(changed[:, t], 0.0, out[:, t - 1] + 1.0)
    return out


def features(data: Data, sim, res: Residuals) -> dict[str, np.ndarray]:
    """Candidate features at the start of each window."""
    obs = np.asarray(data.obs, dtype=np.float64)[res.episode, res.start]
    pad = data.acts.shape[1] - (data.obs.shape[1] - 1)
    acts = np.asarray(data.acts, dtype=np.float64)[:, pad:]  # drop the zeros before episodes
    out = {}
    for i in range(sim.nq):
        joint = sim.obs_names[i].split("_", 1)[1]
        q = obs[:, i]
        if sim.angular[i]:
            out[f"angle {joint}"] = np.angle(np.exp(1j * q))
        else:
            out[f"position {joint}"] = q
        qd = obs[:, sim.nq + i]
        out[f"velocity {joint}"] = qd
        out[f"speed |{joint}|"] = np.abs(qd)
        out[f"sign of velocity {joint}"] = np.sign(qd)
    for a, name in enumerate(sim.action_names):
        out[f"action {name}"] = acts[res.episode, res.start, a]
    since = time_since_change(acts)
    out["time since the action changed (steps)"] = since[res.episode, res.start]
    return out


def eta_squared(feature: np.ndarray, residual: np.ndarray, bins: int) -> float:
    """Share of the residual's variance explained by the feature's bin means."""
    total = np.sum((residual - residual.mean()) ** 2)
    if total <= 0 or len(residual) < 2 * bins:
        return 0.0
    values = np.unique(feature)
    if len(values) <= max(3, bins // 2):
        labels = np.searchsorted(values, feature)
    else:
        edges = np.unique(np.quantile(feature, np.linspace(0, 1, bins + 1)[1:-1]))
        labels = np.searchsorted(edges, feature, side="right")
    counts = np.bincount(labels)
    sums = np.bincount(labels, weights=residual)
    nonzero = counts > 0
    means = sums[nonzero] / counts[nonzero]
    between = np.sum(counts[nonzero] * (means - residual.mean()) ** 2)
    # the expected between-bin variance of pure noise, (bins - 1) / n of the total, removed
    bias = (nonzero.sum() - 1) / len(residual)
    return float(max(between / total - bias, 0.0) / (1 - bias))


def locate(data: Data, sim, res: Residuals, bins: int) -> Location:
    scale = np.asarray(data.scale, dtype=np.float64)
    normalized = res.one_step / scale
    power = np.mean(normalized**2, axis=0)
    share = power / max(power.sum(), 1e-300)
    feats = features(data, sim, res)
    table = []
    for i, var in enumerate(sim.obs_names):
        for name, values in feats.items():
            eta2 = eta_squared(values, res.one_step[:, i], bins)
            table.append(
                {
                    "variable": var,
                    "feature": name,
                    "eta2": eta2,
                    "share": float(share[i]),
                    "score": eta2 * float(share[i]),
                }
            )
    table.sort(key=lambda row: -row["score"])
    return Location(list(sim.obs_names), share, table, feats, res.one_step)
