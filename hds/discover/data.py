"""Measured data prepared for discovery: episodes stacked into device arrays, split into an
identification and a held-out set (and an optional validation dataset), and cut into k-step
windows. Each window set is padded to a multiple of PAD_TO windows, so a compiled function sees
few shapes."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import jax.numpy as jnp
import numpy as np
from scipy import stats

from hds.data.format import Dataset, split_episodes, validate

SETS = ("identification", "heldout", "validation")
MIN_WINDOWS = 8  # fewer identification windows than this cannot identify anything
PAD_TO = 64  # window counts are rounded up to a multiple of this


@dataclass(frozen=True)
class Windows:
    episode: np.ndarray  # [W] int32, index into the stacked episodes
    start: np.ndarray  # [W] int32, the step a window starts from
    mask: np.ndarray  # [W] float32, 0 for padding
    episodes: np.ndarray  # the stacked episodes of this set

    @property
    def count(self) -> int:
        return int(self.mask.sum())


@dataclass(eq=False)
class Data:
    obs: jnp.ndarray  # [E, T+1, n_obs] every episode of every set
    acts: jnp.ndarray  # [E, pad + T, n_act] zeros before each episode (and after short ones)
    scale: jnp.ndarray  # [n_obs] each variable's std on the identification set
    noise: np.ndarray  # [n_obs] estimated measurement noise std (`noise_level`)
    windows: dict  # set name -> Windows
    horizon: int  # k
    dt: float
    obs_names: tuple[str, ...]
    action_names: tuple[str, ...]
    source: dict  # set name -> (dataset name, episode indices in that dataset)
    # [nq] each velocity's error beyond white noise, as a share of its std (`velocity_error`);
    # empty where the record has no pairs of coordinates and velocities
    velocity_error: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def arrays(self, name: str) -> tuple:
        w = self.windows[name]
        return (
            self.obs,
            self.acts,
            jnp.asarray(w.episode),
            jnp.asarray(w.start),
            jnp.asarray(w.mask),
            self.scale,
        )


def noise_level(obs: np.ndarray, order: int = 4) -> np.ndarray:
    """[n_obs] measurement-noise std of each variable of obs [E, T+1, n_obs], estimated from
    the median absolute deviation of its `order`-th time differences. Smooth motion has tiny
    high differences and the rare kinks (an action switching) do not move a median, so what
    is left is white noise, whose order-th difference has variance C(2 order, order) sigma^2.
    Where the sampled motion is not smooth at the sample rate (a velocity under a PRBS, a
    chirp near a quarter of Nyquist) the differences hold the motion too and this
    overestimates, by 2-4x on a cart's velocity at 25 Hz; with a model fitted,
    `hds.discover.design.Designer.sensor_noise` takes the noise from its residuals instead.
    """
    if obs.shape[1] <= order:
        return np.zeros(obs.shape[-1])
    d = np.diff(obs, n=order, axis=1).reshape(-1, obs.shape[-1])
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0) / 0.6745
    return mad / np.sqrt(math.comb(2 * order, order))


SPANS = (1, 2, 4, 8, 16)  # samples over which `velocity_error` compares a change and a mean
# `velocity_error` leaves out this share of the largest gaps: the few samples where the
# velocity does not vary smoothly between samples (stick-slip, an action switching)
KINKS = 0.05
# ... and divides the rest's mean square by what that leaves of white noise's (a chi-square
# of 1 degree below its 95% quantile keeps 76% of its mean): white noise is estimated whole
_KEPT = float(stats.chi2(3).cdf(stats.chi2(1).ppf(1 - KINKS)) / (1 - KINKS))


def _sample_weights(frames: int) -> tuple[np.ndarray, np.ndarray]:
    """The weights alpha of v[t-1], v[t], v[t+1], v[t+2] with which the simulator's `frames`
    semi-implicit Euler steps a sample, (q[t+1] - q[t]) / dt = mean_j qd(t + j dt / frames),
    j = 1 .. frames, hold for every cubic velocity between the samples (one frame: v[t+1])."""
    nodes = np.arange(-1, 3)
    taus = np.arange(1, frames + 1) / frames
    powers = np.arange(len(nodes))
    moments = np.array([np.mean(taus**p) for p in powers])
    return nodes, np.linalg.solve(nodes[None, :].astype(float) ** powers[:, None], moments)


def velocity_error(
    obs: np.ndarray, dt: float, nq: int, frames: int, angular: np.ndarray, noise: np.ndarray
) -> np.ndarray:
    """[nq] the error of each recorded velocity that white noise does not explain, as a share
    of the velocity's std: how far it disagrees with its own coordinate's recorded change.

    `noise_level` sees white noise only; a velocity smoothed or de-noised offline (a median
    filter, wavelets), sampled late or biased carries a smooth error that its high time
    differences do not show, and a measured initial state starts every window from it. The
    coordinate's change is the reference: the simulator takes `frames` semi-implicit Euler
    steps per sample, q[t+1] - q[t] = h (qd_1 + ... + qd_f), which for a velocity that is a
    cubic through the samples t-1 .. t+2 is dt times a weighted sum of them
    (`_sample_weights`; -1/24, 13/24, 13/24, -1/24 for many frames). Not a straight line
    between t and t+1: where the motion's time constants are near a sample (a Furuta arm's
    motor, 20 ms samples), the velocity's curvature within a sample alone gave a noise-free
    record of the plant's own states 0.56% of the arm's std (and a lab draw's, 0.77-0.98%).
    Over a span of s samples the gap g = (q[t+s] - q[t]) / (s dt) minus the mean of those
    means is zero on the simulator's own states up to the motion's fourth derivative, and
    white noise alone gives it the variance 2 s_q^2 / (s dt)^2 + sum(c^2) s_v^2, c the
    velocities' coefficients in the mean (s_q, s_v: `noise`). Returned: sqrt(mean g^2 - that)
    / std(qd) at the shortest span of `SPANS` where the error beyond noise is at least the
    noise's own part (the closest to one sample's error that the record can measure: a noisy
    coordinate needs a longer span), and 0 where no span shows it. The mean square leaves out
    the largest `KINKS` of the gaps (where stick-slip or a switching action bends the velocity
    within a sample) and no more: a smooth error gathers where the motion turns, which a
    median would drop. A record whose coordinates and velocities differ in number (ball or
    free joints), or too short for the weights, gives an empty array.
    """
    nodes, alpha = _sample_weights(frames)
    first, last = -int(nodes[0]), int(nodes[-1])
    if obs.shape[-1] != 2 * nq or obs.shape[1] < 2 + first + last:
        return np.zeros(0)
    out = np.zeros(nq)
    for i in range(nq):
        q = np.unwrap(obs[..., i], axis=1) if angular[i] else obs[..., i]
        v = obs[..., nq + i]
        std = v.std()
        if std == 0:
            continue
        # each sample's mean velocity, for the samples [t, t+1] with a neighbour on each side
        samples = np.arange(first, v.shape[1] - last)
        mean = sum(a * v[:, samples + k] for k, a in zip(nodes, alpha, strict=True))
        q = q[:, first : v.shape[1] - last + 1]
        total = np.concatenate([np.zeros((len(v), 1)), np.cumsum(mean, axis=1)], axis=1)
        for s in (s for s in SPANS if s <= mean.shape[1]):
            gap = (q[:, s:] - q[:, :-s]) / (s * dt) - (total[:, s:] - total[:, :-s]) / s
            weights = np.convolve(np.ones(s), alpha) / s
            white = 2 * noise[i] ** 2 / (s * dt) ** 2 + np.sum(weights**2) * noise[nq + i] ** 2
            squares = np.sort(gap.ravel() ** 2)
            square = float(squares[: max(1, int(len(squares) * (1 - KINKS)))].mean()) / _KEPT
            if square >= 2 * white:
                out[i] = np.sqrt(square - white) / std
                break
    return out


def check_size(dataset: Dataset, horizon: int, where: str = "dataset") -> None:
    if dataset.n_episodes < 2 or dataset.horizon < horizon:
        raise ValueError(
            f"{where} is too short to identify anything: it has {dataset.n_episodes} episode(s) "
            f"of {dataset.horizon} steps, and discovery needs at least 2 episodes (one is held "
            f"out to judge each effect) of at least k = {horizon} steps (discover.horizon): "
            "record more or longer episodes, split a long record into episodes, or lower "
            "discover.horizon"
        )


def _starts(length: int, horizon: int, stride: int) -> np.ndarray:
    return np.arange(0, length - horizon + 1, stride, dtype=np.int32)


def prepare(
    dataset: Dataset,
    sim,
    pad: int,
    horizon: int,
    stride: int,
    heldout_fraction: float,
    seed: int,
    validation: Dataset | None = None,
) -> Data:
    """Check the datasets against the simulator and lay them out for the compiled functions."""
    validate(dataset, sim, "dataset")
    check_size(dataset, horizon)
    if validation is not None:
        validate(validation, sim, "validation dataset")
        if validation.dt != dataset.dt:
            raise ValueError(
                f"the validation dataset's dt = {validation.dt} s differs from the "
                f"dataset's {dataset.dt} s: resample one of them"
            )
        if validation.horizon < horizon:
            raise ValueError(
                f"the validation dataset's episodes have {validation.horizon} "
                f"steps, fewer than k = {horizon} (discover.horizon)"
            )
    ident, held = split_episodes(dataset.n_episodes, heldout_fraction, seed, "discovery")
    parts = [dataset] + ([validation] if validation is not None else [])
    t_max = max(d.horizon for d in parts)
    obs, acts, lengths = [], [], []
    for d in parts:
        obs.append(np.pad(d.obs, ((0, 0), (0, t_max - d.horizon), (0, 0))))
        acts.append(np.pad(d.actions, ((0, 0), (pad, t_max - d.horizon), (0, 0))))
        lengths += [d.horizon] * d.n_episodes
    obs, acts = np.concatenate(obs), np.concatenate(acts)
    members = {"identification": ident, "heldout": held}
    source = {"identification": ("dataset", ident), "heldout": ("dataset", held)}
    if validation is not None:
        members["validation"] = dataset.n_episodes + np.arange(validation.n_episodes)
        source["validation"] = ("validation", np.arange(validation.n_episodes))
    starts = {
        name: [(e, t) for e in eps for t in _starts(lengths[e], horizon, stride)]
        for name, eps in members.items()
    }
    if len(starts["identification"]) < MIN_WINDOWS:
        raise ValueError(
            f"the dataset is too short to identify anything: its identification episodes give "
            f"{len(starts['identification'])} windows of k = {horizon} steps (at least "
            f"{MIN_WINDOWS} are needed): record more or longer episodes, or lower "
            "discover.horizon or discover.stride"
        )
    windows = {}
    for name, pairs in starts.items():
        pairs = np.array(pairs, dtype=np.int32).reshape(-1, 2)
        n = len(pairs)
        # each set to its own multiple of PAD_TO: a held-out set of a quarter of the episodes
        # padded to the identification set's length would cost each of its errors (19 rows a
        # round) three times its windows; a set's compiled programs are the forward's alone
        size = PAD_TO * -(-max(n, 1) // PAD_TO)
        windows[name] = Windows(
            episode=np.pad(pairs[:, 0], (0, size - n)),
            start=np.pad(pairs[:, 1], (0, size - n)),
            mask=np.pad(np.ones(n, np.float32), (0, size - n)),
            episodes=members[name],
        )
    ident_obs = dataset.obs[ident].reshape(-1, dataset.n_obs)
    std = ident_obs.std(axis=0)
    scale = np.maximum(std, 1e-6 * std.max() + 1e-12)
    noise = noise_level(dataset.obs[ident])
    return Data(
        obs=jnp.asarray(obs, jnp.float32),
        acts=jnp.asarray(acts, jnp.float32),
        scale=jnp.asarray(scale, jnp.float32),
        noise=noise,
        windows=windows,
        horizon=int(horizon),
        dt=dataset.dt,
        obs_names=tuple(sim.obs_names),
        action_names=tuple(sim.action_names),
        source=source,
        velocity_error=velocity_error(
            dataset.obs[ident], dataset.dt, sim.nq, sim.frames, np.asarray(sim.angular), noise
        ),
    )
