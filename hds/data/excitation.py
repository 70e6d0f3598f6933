"""Excitation signals for system identification: open-loop controls within actuator limits.

Every signal has the signature

  signal(seed, n_episodes, horizon, dt, ctrl_range, **params) -> u [n_episodes, horizon, n_act]

`seed` is an int, a numpy Generator, or a JAX PRNG key (turned into a numpy seed): the same
seed gives the same numbers. `ctrl_range` [n_act, 2] are the actuator limits (low, high), which
must be finite; every value lies within them. `scale` (0, 1] shrinks the amplitude around the
middle of the range. Each (episode, actuator) pair gets its own random draw.

  random_steps  piecewise constant: levels uniform in the range, each held for a random time
                uniform in [min_hold, max_hold] seconds
  chirp         a sine whose frequency sweeps linearly from f0 to f1 Hz over the episode
                (scipy.signal.chirp; f1 defaults to 1 / (8 dt), a quarter of the Nyquist
                frequency), random phase
  prbs          pseudo-random binary sequence: a maximum-length sequence
                (scipy.signal.max_len_seq) between the two levels (middle +- scale * half
                range), one bit every bit_time seconds; each pair starts the register at a
                random non-zero state

Pass an array of them as the controller of `hds.data.collect` (or `hds.real.rollout`).
"""

from __future__ import annotations

import math

import numpy as np

# Register lengths scipy.signal.max_len_seq has feedback taps for without being given any.
PRBS_ORDERS = range(4, 33)


def make_rng(seed) -> np.random.Generator:
    """A numpy Generator from an int, a Generator (returned as is) or a JAX PRNG key."""
    if isinstance(seed, np.random.Generator):
        return seed
    if isinstance(seed, int | np.integer):
        return np.random.default_rng(int(seed))
    try:  # a JAX key: typed (jax.random.key) or raw uint32 (jax.random.PRNGKey)
        import jax

        data = (
            jax.random.key_data(seed)
            if jax.dtypes.issubdtype(seed.dtype, jax.dtypes.prng_key)
            else seed
        )
        return np.random.default_rng(np.asarray(data, dtype=np.uint32).ravel().tolist())
    except (AttributeError, TypeError, ValueError):
        raise TypeError(
            f"seed must be an int, a numpy Generator or a JAX PRNG key, not {type(seed).__name__}"
        ) from None


def _setup(n_episodes, horizon, dt, ctrl_range, scale):
    ctrl_range = np.asarray(ctrl_range, dtype=np.float64)
    if ctrl_range.ndim != 2 or ctrl_range.shape[1] != 2 or ctrl_range.shape[0] < 1:
        raise ValueError(
            f"ctrl_range has shape {ctrl_range.shape}; it must be [n_act, 2] "
            "(low, high per actuator)"
        )
    if not np.isfinite(ctrl_range).all():
        bad = np.flatnonzero(~np.isfinite(ctrl_range).all(1)).tolist()
        raise ValueError(
            f"actuator(s) {bad} have no finite limits (ctrl_range "
            f"{ctrl_range.tolist()}): give finite limits to excite within, "
            "e.g. ctrl_range=[[-1, 1]]"
        )
    if (ctrl_range[:, 0] >= ctrl_range[:, 1]).any():
        raise ValueError(f"ctrl_range {ctrl_range.tolist()} has low >= high for some actuator")
    if int(n_episodes) < 1 or int(horizon) < 1:
        raise ValueError(f"n_episodes = {n_episodes} and horizon = {horizon} must be >= 1")
    if not dt > 0:
        raise ValueError(f"dt = {dt} must be positive (seconds per step)")
    if not 0 < scale <= 1:
        raise ValueError(f"scale = {scale} must lie in (0, 1] (fraction of the half range)")
    middle = ctrl_range.mean(1)
    half = 0.5 * (ctrl_range[:, 1] - ctrl_range[:, 0]) * scale
    return ctrl_range, middle, half


def _clip(u, ctrl_range):
    return np.clip(u, ctrl_range[:, 0], ctrl_range[:, 1])


def random_steps(
    seed,
    n_episodes: int,
    horizon: int,
    dt: float,
    ctrl_range,
    min_hold=0.2,
    max_hold=1.0,
    scale=1.0,
) -> np.ndarray:
    """Piecewise-constant levels, uniform in the range, held min_hold..max_hold seconds each."""
    ctrl_range, middle, half = _setup(n_episodes, horizon, dt, ctrl_range, scale)
    if not 0 < min_hold <= max_hold:
        raise ValueError(
            f"hold times must satisfy 0 < min_hold <= max_hold (seconds); got "
            f"min_hold = {min_hold}, max_hold = {max_hold}"
        )
    rng = make_rng(seed)
    n_act = len(ctrl_range)
    lo_steps = max(1, round(min_hold / dt))
    hi_steps = max(lo_steps, round(max_hold / dt))
    n_holds = math.ceil(horizon / lo_steps)  # enough holds to cover the horizon
    holds = rng.integers(lo_steps, hi_steps + 1, size=(n_episodes, n_act, n_holds))
    levels = rng.uniform(-1.0, 1.0, size=(n_episodes, n_act, n_holds))
    ends = np.cumsum(holds, axis=-1).reshape(-1, n_holds)  # step at which each hold ends
    steps = np.arange(horizon)
    index = np.stack([np.searchsorted(row, steps, side="right") for row in ends])
    u = np.take_along_axis(levels, index.reshape(n_episodes, n_act, horizon), axis=-1)
    u = middle[:, None] + half[:, None] * u
    return _clip(np.moveaxis(u, 1, 2), ctrl_range)


def chirp(
    seed, n_episodes: int, horizon: int, dt: float, ctrl_range, f0=0.1, f1=None, scale=1.0
) -> np.ndarray:
    """A sine sweeping linearly from f0 to f1 Hz over the horizon, random phase per pair."""
    ctrl_range, middle, half = _setup(n_episodes, horizon, dt, ctrl_range, scale)
    nyquist = 0.5 / dt
    f1 = 0.25 * nyquist if f1 is None else f1
    if not (0 <= f0 <= nyquist and 0 <= f1 <= nyquist):
        raise ValueError(
            f"chirp frequencies f0 = {f0} Hz, f1 = {f1} Hz must lie in "
            f"[0, {nyquist}] Hz (the Nyquist frequency of dt = {dt} s)"
        )
    rng = make_rng(seed)
    n_act = len(ctrl_range)
    phase0 = rng.uniform(0.0, 360.0, size=(n_episodes, 1, n_act))  # degrees, as scipy takes
    t = (np.arange(horizon) * dt)[None, :, None]
    # scipy's chirp is a cosine; a phase of -90 degrees makes it the sine from phase0
    from scipy import signal  # here, not at the top: ~1 s of every process (hds.gap)

    wave = signal.chirp(t, f0=f0, t1=horizon * dt, f1=f1, method="linear", phi=phase0 - 90.0)
    return _clip(middle + half * wave, ctrl_range)


def prbs(
    seed, n_episodes: int, horizon: int, dt: float, ctrl_range, bit_time=None, order=None, scale=1.0
) -> np.ndarray:
    """Maximum-length pseudo-random binary sequence (scipy.signal.max_len_seq) between
    middle +- scale * half range, one bit per bit_time seconds (default dt); order (register
    length) defaults to the shortest whose period covers the horizon, at least 4."""
    ctrl_range, middle, half = _setup(n_episodes, horizon, dt, ctrl_range, scale)
    bit_time = dt if bit_time is None else bit_time
    if not bit_time > 0:
        raise ValueError(f"bit_time = {bit_time} must be positive (seconds per bit)")
    bit_steps = max(1, round(bit_time / dt))
    n_bits = math.ceil(horizon / bit_steps)
    if order is None:
        order = next((n for n in PRBS_ORDERS if 2**n - 1 >= n_bits), max(PRBS_ORDERS))
    if order not in PRBS_ORDERS:
        raise ValueError(
            f"PRBS order {order} is not supported; choose one of {PRBS_ORDERS.start} to "
            f"{PRBS_ORDERS.stop - 1}"
        )
    rng = make_rng(seed)
    n_act = len(ctrl_range)
    # a random non-zero register per (episode, actuator): a random shift of the sequence
    start = rng.integers(1, 2**order, size=n_episodes * n_act)
    states = (start[:, None] >> np.arange(order)) & 1
    from scipy import signal  # here, not at the top: ~1 s of every process (hds.gap)

    bits = np.stack([signal.max_len_seq(order, state=s, length=n_bits)[0] for s in states])
    bits = np.repeat(bits, bit_steps, axis=1)[:, :horizon].reshape(n_episodes, n_act, horizon)
    u = middle[:, None] + half[:, None] * (2.0 * bits - 1.0)
    return _clip(np.moveaxis(u, 1, 2), ctrl_range)


SIGNALS = {"steps": random_steps, "chirp": chirp, "prbs": prbs}


def excitation(kind: str, seed, n_episodes: int, horizon: int, dt: float, ctrl_range, **params):
    """One of SIGNALS by name (steps, chirp, prbs)."""
    if kind not in SIGNALS:
        raise ValueError(f"unknown excitation '{kind}'; choose one of {list(SIGNALS)}")
    return SIGNALS[kind](seed, n_episodes, horizon, dt, ctrl_range, **params)
