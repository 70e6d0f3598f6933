"""The multi-arm pendulum: real free-swing recordings of a laboratory single and double pendulum,
as `Dataset`s.

K. Kaheman, U. Fasel, J. J. Bramburger, B. Strom, J. N. Kutz, S. L. Brunton, "The Experimental
Multi-Arm Pendulum on a Cart: A Benchmark System for Chaos, Learning, and Control",
arXiv:2205.06231 (2022), MIT licence (cite it wherever the data is used). The files live in
../shared/data/multiarm_pendulum/ next to the repository (`paths.shared`), not in it.

The published layout, read as it is (any number of arms n):
  Y_id   object array of segments, each a float array [2n, T_e]: the n arms' angles, then their
         n angular velocities; the identification episodes
  Y_vad  the same: the held-out (validation) episodes, never used in a fit
  dt     the sampling period, s (0.001)
Angles are each arm's in the WORLD frame, from the upright (hanging down is pi), rad; velocities
rad/s (the authors' de-noised ones).

What the reader does with them, all in this one place:
  - world -> joint angles (`to_joint`): an MJCF's hinge of arm i > 1 turns relative to arm
    i - 1, so q_i = phi_i - phi_{i-1} (and qd likewise); arm 1's hinge is its world angle. Its
    inverse is `to_world`. Hanging still is q = (pi, 0, ..., 0).
  - each set's segments are cut to the set's shortest one (a Dataset's episodes share one T;
    the published segments differ by at most a few samples: 9167 and 9166, 2667 and 2658);
  - decimation to `dt` (a whole multiple of the record's period): every factor-th sample;
  - no actions: the arms swing free (the cart is locked), so the systems (multiarm_*.xml) carry
    one unlimited motor, `pivot`, on the first hinge, and the reader gives it zero: an episode
    of T steps has actions zeros [T, 1], exactly no torque. (A Dataset has at least one action,
    and the discovery and training code then need no case for an unactuated system.)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hds.data.format import Dataset

SETS = ("Y_id", "Y_vad")  # identification, held-out
SAMPLE_DT = 1e-3  # s, the published recordings' period
ACTION_NAMES = ("pivot",)
LAYOUT = (
    "the multi-arm pendulum's layout is Y_id and Y_vad (object arrays of segments, each "
    "[2n, T]: n angles then n velocities) and dt"
)


def obs_names(arms: int) -> tuple[str, ...]:
    """The systems' observation names: q_arm1 .. q_armn, then qd_arm1 .. qd_armn."""
    joints = [f"arm{i + 1}" for i in range(arms)]
    return tuple([f"q_{j}" for j in joints] + [f"qd_{j}" for j in joints])


def to_joint(world: np.ndarray) -> np.ndarray:
    """[..., 2n] world angles and velocities (phi, dphi) -> the MJCF's joint coordinates (q, qd):
    q_1 = phi_1, q_i = phi_i - phi_{i-1} for i > 1 (each hinge turns relative to the arm above)."""
    world = np.asarray(world, dtype=np.float64)
    n = world.shape[-1] // 2
    out = world.copy()
    for block in (slice(0, n), slice(n, 2 * n)):
        part = world[..., block]
        out[..., block] = np.concatenate([part[..., :1], np.diff(part, axis=-1)], axis=-1)
    return out


def to_world(joint: np.ndarray) -> np.ndarray:
    """The inverse of `to_joint`: phi_i = q_1 + ... + q_i (and dphi likewise)."""
    joint = np.asarray(joint, dtype=np.float64)
    n = joint.shape[-1] // 2
    out = joint.copy()
    for block in (slice(0, n), slice(n, 2 * n)):
        out[..., block] = np.cumsum(joint[..., block], axis=-1)
    return out


def read_mat(path: str | Path) -> dict:
    """{'Y_id': [segments [2n, T_e]], 'Y_vad': [...], 'dt': float, 'arms': n}, checked."""
    from scipy.io import loadmat

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"no multi-arm pendulum file at {path}: the published files live in "
            "<paths.shared>/data/multiarm_pendulum (set HDS_SHARED to the folder holding data/)"
        )
    try:
        raw = loadmat(str(path), squeeze_me=True)
    except Exception as err:  # scipy raises several types for damaged files
        raise ValueError(
            f"{path} is not a readable MATLAB file ({type(err).__name__}: {err})"
        ) from None
    present = sorted(k for k in raw if not k.startswith("__"))
    missing = [k for k in (*SETS, "dt") if k not in raw]
    if missing:
        raise ValueError(f"{path} lacks {missing}: {LAYOUT}; it has {present}")
    dt = np.asarray(raw["dt"], dtype=np.float64)
    if dt.size != 1 or not np.isfinite(dt).all() or float(dt) <= 0:
        raise ValueError(f"{path}: dt = {raw['dt']!r} must be one positive number of seconds")
    out, rows = {"dt": float(dt)}, set()
    for key in SETS:
        segments = raw[key]
        if not (isinstance(segments, np.ndarray) and segments.dtype == object):
            segments = [segments]  # a set of one segment is squeezed to the segment itself
        arrays = []
        for e, seg in enumerate(segments):
            seg = np.asarray(seg)
            if seg.ndim != 2 or seg.shape[0] % 2 or seg.shape[0] == 0 or seg.shape[1] < 2:
                raise ValueError(
                    f"{path}: {key} segment {e} has shape {seg.shape}; {LAYOUT}, with an even "
                    "number of rows and at least two samples"
                )
            if not np.issubdtype(seg.dtype, np.number) or not np.isfinite(seg).all():
                raise ValueError(f"{path}: {key} segment {e} holds non-finite or non-numbers")
            rows.add(seg.shape[0])
            arrays.append(seg.astype(np.float64))
        out[key] = arrays
    if len(rows) != 1:
        raise ValueError(
            f"{path}: its segments have {sorted(rows)} rows; {LAYOUT}, the same n in every one"
        )
    out["arms"] = rows.pop() // 2
    return out


def load(path: str | Path, dt: float | None = None) -> tuple[Dataset, Dataset]:
    """(identification, held-out) datasets of a published file, in the systems' joint
    coordinates, sampled every `dt` s (default: the record's own period)."""
    raw = read_mat(path)
    period = raw["dt"]
    dt = period if dt is None else float(dt)
    ratio = dt / period
    factor = round(ratio)
    if factor < 1 or abs(ratio - factor) > 1e-9:
        raise ValueError(f"dt = {dt} s must be a whole multiple of the record's {period} s")
    names = obs_names(raw["arms"])
    out = []
    for key in SETS:
        length = min(seg.shape[1] for seg in raw[key])
        steps = (length - 1) // factor
        if steps < 1:
            raise ValueError(f"{path}: {key}'s shortest segment is shorter than dt = {dt} s")
        obs = np.stack([to_joint(seg[:, : steps * factor + 1 : factor].T) for seg in raw[key]])
        actions = np.zeros((obs.shape[0], steps, 1))
        out.append(Dataset(obs, actions, factor * period, names, ACTION_NAMES))
    return out[0], out[1]


def read_parameters(path: str | Path) -> np.ndarray:
    """The authors' `EstimatedParameters` vector (the order of `SINGLE` or `DOUBLE`)."""
    from scipy.io import loadmat

    raw = loadmat(str(path), squeeze_me=True)
    if "EstimatedParameters" not in raw:
        raise ValueError(f"{path} lacks EstimatedParameters (the authors' fitted parameters)")
    return np.asarray(raw["EstimatedParameters"], dtype=np.float64).ravel()


# The authors' parameters, in their files' order (README of the data; hds/envs/assets
# multiarm_single.xml and multiarm_double.xml are built from them, without the damping).
SINGLE = ("a1", "m1", "I1", "k1", "g")
DOUBLE = ("m1", "m2", "a1", "a2", "L1", "I1", "I2", "k1", "k2", "g")
PUBLISHED = {  # the files' values to 8 digits (the data README rounds them to 5)
    1: dict(zip(SINGLE, (0.14775490, 0.14758457, 1.0911851e-4, 2.2394013e-4, 9.8100131))),
    2: dict(
        zip(
            DOUBLE,
            (0.093843975, 0.13759597, 0.10856521, 0.11677902, 0.17271920)
            + (4.3752943e-4, 1.2688294e-3, 2.3714278e-4, 1.0000002e-5, 9.8085802),
        )
    ),
}


def published_effects(arms: int) -> list[dict]:
    """The authors' viscous damping as the library's effects on multiarm_single/double.xml
    (their fit = the MJCF plus these): viscous_damping on each hinge, the relative velocity's
    law being exactly MuJoCo's joint damping."""
    p = PUBLISHED[arms]
    return [
        {
            "name": "viscous_damping",
            "target": f"arm{i + 1}",
            "params": {"coefficient": p[f"k{i + 1}"]},
        }
        for i in range(arms)
    ]
