"""EMPS: real measurements of a motor-driven linear axis with friction, as a `Dataset`.

A. Janot, M. Gautier, M. Brunot, "Data Set and Reference Models of EMPS", Nonlinear System
Identification Benchmarks workshop, 2019 (cite it wherever the data is used). The files
(DATA_EMPS.mat: estimation, DATA_EMPS_PULSES.mat: validation) are not part of this project;
they live in ../shared/data/emps/ next to the repository (`paths.shared`, conf/paths/).

The system is one prismatic joint driven by the motor force gtau * vir (the MJCF
hds/envs/assets/emps.xml, whose actuator gear is gtau, so the action is the voltage vir). Only
the position qm is measured; the velocity is estimated as the benchmark's reference method
does: qm low-pass filtered by a 4th-order Butterworth at 100 Hz, forward and backward (zero
phase), then differentiated centrally. The 1 kHz record is then
  - decimated to `dt` (observations: the filtered position and the velocity estimate at every
    dt; actions: the MEAN voltage over each interval, which carries the interval's impulse);
  - cut into episodes of `segment` seconds (consecutive episodes share their boundary sample),
    so the record can be split into identification and held-out episodes.
The data is closed loop (a position controller computed vir from qm), which is why discovery
drives the simulator with the measured voltage over short horizons from measured states.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hds.data.format import Dataset

ESTIMATION, VALIDATION = "DATA_EMPS.mat", "DATA_EMPS_PULSES.mat"
SAMPLE_DT = 1e-3  # s, the record's sampling period
# The benchmark's reference model: M qdd = gtau vir - Fv qd - Fc sign(qd) - offset
PUBLISHED = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "offset": -3.1648, "gtau": 35.1507}
UNITS = {"M": "kg", "Fv": "N s/m", "Fc": "N", "offset": "N", "gtau": "N/V"}
OBS_NAMES, ACTION_NAMES = ("q_axis", "qd_axis"), ("motor",)


def read_mat(path: str | Path) -> dict[str, np.ndarray]:
    """The signals of an EMPS .mat file as flat float arrays (t, qm, vir, gtau, ...)."""
    from scipy.io import loadmat

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"no EMPS file at {path}: the benchmark's files live in <paths.shared>/data/emps "
            "(conf/paths/default.yaml; set HDS_SHARED to the folder holding data/emps)"
        )
    try:
        raw = loadmat(str(path))
    except Exception as err:  # scipy raises several types for damaged files
        raise ValueError(
            f"{path} is not a readable MATLAB file ({type(err).__name__}: {err})"
        ) from None
    missing = [k for k in ("t", "qm", "vir", "gtau") if k not in raw]
    if missing:
        present = sorted(k for k in raw if not k.startswith("__"))
        raise ValueError(
            f"{path} lacks the EMPS signal(s) {missing}: an EMPS file holds t, qm, "
            f"vir, gtau (and qg, kp, kv); it has {present}"
        )
    signals = {
        k: np.asarray(v, dtype=np.float64).ravel() for k, v in raw.items() if not k.startswith("__")
    }
    n = len(signals["t"])
    for k in ("qm", "vir"):
        if len(signals[k]) != n or not np.isfinite(signals[k]).all():
            raise ValueError(f"{path}: signal {k} must hold {n} finite samples, like t")
    return signals


def estimate_velocity(q: np.ndarray, dt: float, cutoff: float = 100.0, order: int = 4):
    """(filtered position, velocity): zero-phase Butterworth low-pass, central differences."""
    from scipy.signal import butter, filtfilt

    nyquist = 0.5 / dt
    if not 0 < cutoff < nyquist:
        raise ValueError(
            f"cutoff = {cutoff} Hz must lie in (0, {nyquist}) Hz, the Nyquist "
            f"frequency of dt = {dt} s"
        )
    b, a = butter(order, cutoff / nyquist)
    smooth = filtfilt(b, a, q)
    return smooth, np.gradient(smooth, dt)


def load(
    path: str | Path, dt: float = 0.005, segment: float = 1.0, cutoff: float = 100.0, order: int = 4
) -> Dataset:
    """An EMPS record as episodes of `segment` seconds sampled every `dt` seconds."""
    signals = read_mat(path)
    t = signals["t"]
    step = float(np.median(np.diff(t)))
    if abs(step - SAMPLE_DT) > 1e-6:
        raise ValueError(f"{path}: samples are {step} s apart; EMPS records are sampled at 1 kHz")
    ratio = dt / SAMPLE_DT
    factor = round(ratio)
    if factor < 1 or abs(ratio - factor) > 1e-9:
        raise ValueError(f"dt = {dt} s must be a whole multiple of the record's {SAMPLE_DT} s")
    steps = round(segment / dt)
    if steps < 1:
        raise ValueError(f"segment = {segment} s is shorter than dt = {dt} s")
    q, qd = estimate_velocity(signals["qm"], SAMPLE_DT, cutoff, order)
    vir = signals["vir"]
    n_intervals = (len(q) - 1) // factor  # whole decimated intervals in the record
    obs = np.stack([q, qd], axis=1)[: n_intervals * factor + 1 : factor]
    actions = vir[: n_intervals * factor].reshape(n_intervals, factor).mean(axis=1)
    episodes = n_intervals // steps
    if episodes < 1:
        raise ValueError(
            f"{path} holds {n_intervals * dt:.3g} s, less than one segment of {segment} s"
        )
    ep_obs = np.stack([obs[e * steps : (e + 1) * steps + 1] for e in range(episodes)])
    ep_act = np.stack([actions[e * steps : (e + 1) * steps, None] for e in range(episodes)])
    return Dataset(ep_obs, ep_act, dt, OBS_NAMES, ACTION_NAMES)


def published_effects() -> dict[str, dict]:
    """The published friction and offset as the library's effects on emps.xml, by effect key:
    Coulomb and viscous friction on joint `axis`, and the offset as a constant added to the
    voltage (force = gtau (vir + o), so o = -offset / gtau volts)."""
    p = PUBLISHED
    return {
        "coulomb_friction@axis": {"force": p["Fc"]},
        "viscous_damping@axis": {"coefficient": p["Fv"]},
        "actuator_offset@motor": {"offset": -p["offset"] / p["gtau"]},
    }


def idim_ls(path: str | Path, cutoff: float = 100.0, order: int = 4) -> dict[str, float]:
    """The benchmark's reference identification, IDIM-LS (inverse dynamic identification model,
    least squares) on one EMPS record: qm filtered as `estimate_velocity` does, differentiated
    twice centrally, and gtau vir = M qdd + Fv qd + Fc sign(qd) + offset solved by least
    squares at every 1 kHz sample. Returns M, Fv, Fc, offset (the keys of PUBLISHED) and
    `relative_error`, the norm of the force residual over the norm of the force."""
    signals = read_mat(path)
    _, qd = estimate_velocity(signals["qm"], SAMPLE_DT, cutoff, order)
    qdd = np.gradient(qd, SAMPLE_DT)
    force = float(signals["gtau"][0]) * signals["vir"]
    regressors = np.stack([qdd, qd, np.sign(qd), np.ones_like(qd)], axis=1)
    theta, *_ = np.linalg.lstsq(regressors, force, rcond=None)
    residual = force - regressors @ theta
    fitted = dict(zip(("M", "Fv", "Fc", "offset"), theta.tolist()))
    return fitted | {"relative_error": float(np.linalg.norm(residual) / np.linalg.norm(force))}
