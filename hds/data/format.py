"""Measured data: the `Dataset` and its two file formats. This docstring is the data contract.

A dataset is E episodes of T steps, sampled every `dt` seconds:

  obs      float [E, T+1, n_obs]  obs[e, k] is observed at time k * dt (k = 0 .. T)
  actions  float [E, T, n_act]    actions[e, k] is applied from obs[e, k] until obs[e, k+1]
  dt       float > 0              seconds between two observations (and between two actions)
  obs_names, action_names         tuples of str, or None when unknown

(`Dataset` stores obs and actions as float64 whatever it is given.)

So the transition k of episode e is (obs[e, k], actions[e, k]) -> obs[e, k+1]: an episode has
one more observation than it has actions, and no action follows its last observation.
For a system of hds.envs, obs_names are the joints' positions then velocities
(q_slider, q_hinge, qd_slider, qd_hinge for the cart-pole) and action_names its actuators
(slide); `validate` checks a dataset against a simulator.

File formats, chosen by the extension of the path (`save`, `load`):

.npz (NumPy archive, numpy.savez_compressed; read with allow_pickle=False)
  obs           float array [E, T+1, n_obs]
  actions       float array [E, T, n_act]
  dt            float scalar, seconds
  obs_names     (optional) str array [n_obs]
  action_names  (optional) str array [n_act]

.csv (comma separated, one header line, then one row per observation)
  header:  episode,t,<observation columns>,<action columns>
  - `episode`: a label of the episode (save writes 0 .. E-1). An episode's rows are consecutive
    and in time order; episodes come in file order.
  - `t`: time in seconds, evenly spaced within an episode; save writes t = k * dt from 0.
    dt is read as t[1] - t[0] of the first episode, and every step of every episode must
    match it (within 1e-6 dt, plus the rounding of t): resample uneven logs before saving.
  - action columns are the columns whose name starts with `u_`, and they come after every
    observation column: the action name is the column name without `u_` (column u_slide is
    action slide). Every other column after `t` is an observation, named as its column.
  - each episode has T+1 rows (T >= 1, the same T for every episode). Row k holds obs[e, k]
    and actions[e, k]; the last row of an episode (k = T) holds the final observation and its
    action cells are EMPTY. Every other cell holds a number (nan and inf are read as such,
    and `validate` rejects them).
  - a dataset without names is written with the placeholder columns obs_0, obs_1, ... and
    u_0, u_1, ...; exactly these placeholders are read back as "no names" (None).
  Floats are written with Python's repr, so a save/load round trip is exact.

Writes are atomic: the file is written to a temporary file in the same directory and moved
into place with os.replace, so a crash never leaves a half-written dataset. Every problem with
a file or a dataset raises a ValueError (FileNotFoundError for a missing file) that says what is
wrong, where, and how to fix it.
"""

from __future__ import annotations

import contextlib
import csv
import io
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hds.utils.io import file_mode

ACTION_PREFIX = "u_"
OBS_PLACEHOLDER = "obs_"
FORMATS = (".npz", ".csv")
DT_RTOL = 1e-6  # relative tolerance on dt: even spacing of t, multiple of the physics timestep


@dataclass(eq=False)
class Dataset:
    """E episodes of measured observations and the actions applied between them."""

    obs: np.ndarray  # [E, T+1, n_obs]
    actions: np.ndarray  # [E, T, n_act]
    dt: float  # seconds between observations
    obs_names: tuple[str, ...] | None = None
    action_names: tuple[str, ...] | None = None

    def __post_init__(self):
        self.obs = np.asarray(self.obs, dtype=np.float64)
        self.actions = np.asarray(self.actions, dtype=np.float64)
        self.dt = float(self.dt)
        if self.obs_names is not None:
            self.obs_names = tuple(str(n) for n in self.obs_names)
        if self.action_names is not None:
            self.action_names = tuple(str(n) for n in self.action_names)

    @property
    def n_episodes(self) -> int:
        return self.obs.shape[0]

    @property
    def horizon(self) -> int:
        """T, the number of actions (steps) per episode."""
        return self.actions.shape[1]

    @property
    def n_obs(self) -> int:
        return self.obs.shape[-1]

    @property
    def n_act(self) -> int:
        return self.actions.shape[-1]

    @property
    def times(self) -> np.ndarray:
        """[T+1] time of each observation, seconds from the episode's start."""
        return np.arange(self.obs.shape[1]) * self.dt

    def transitions(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """All E*T transitions (obs [N, n_obs], action [N, n_act], next obs [N, n_obs])."""
        return (
            self.obs[:, :-1].reshape(-1, self.n_obs),
            self.actions.reshape(-1, self.n_act),
            self.obs[:, 1:].reshape(-1, self.n_obs),
        )


# ---------------------------------------------------------------------------------------------
# checks


def concatenate(datasets: list[Dataset]) -> Dataset:
    """The episodes of several datasets of one system, in order, as one."""
    first = datasets[0]
    return Dataset(
        np.concatenate([d.obs for d in datasets]),
        np.concatenate([d.actions for d in datasets]),
        first.dt,
        first.obs_names,
        first.action_names,
    )


def check(dataset: Dataset, where: str = "dataset") -> None:
    """Check that a dataset is consistent in itself (shapes, T, names, dt); no system needed."""
    obs, actions = dataset.obs, dataset.actions
    if obs.ndim != 3:
        raise ValueError(
            f"{where}: obs has shape {obs.shape}; it must be [episodes, T+1, n_obs] "
            "(3 dimensions): add an episode axis for a single episode"
        )
    if actions.ndim != 3:
        raise ValueError(
            f"{where}: actions have shape {actions.shape}; they must be "
            "[episodes, T, n_act] (3 dimensions): add an episode axis for a single "
            "episode, and an action axis for a single actuator"
        )
    if obs.shape[0] == 0 or obs.shape[2] == 0 or actions.shape[2] == 0:
        raise ValueError(
            f"{where} is empty: obs {obs.shape}, actions {actions.shape}; it needs "
            "at least one episode, one observed variable and one action"
        )
    if obs.shape[0] != actions.shape[0]:
        raise ValueError(
            f"{where}: obs hold {obs.shape[0]} episodes and actions "
            f"{actions.shape[0]}: give both the same episodes"
        )
    if obs.shape[1] != actions.shape[1] + 1:
        raise ValueError(
            f"{where}: obs have {obs.shape[1]} steps and actions {actions.shape[1]}; an episode "
            f"of T actions has T+1 observations (the last one follows the last action), so obs "
            f"need {actions.shape[1] + 1} steps: check for an off-by-one"
        )
    if actions.shape[1] < 1:
        raise ValueError(
            f"{where} is empty: its episodes have no step (T = 0); record at least "
            "two observations and the action between them"
        )
    if not np.isfinite(dataset.dt) or dataset.dt <= 0:
        raise ValueError(
            f"{where}: dt = {dataset.dt} must be a positive number of seconds "
            "(the time between two observations)"
        )
    for kind, names, size in (
        ("obs_names", dataset.obs_names, obs.shape[2]),
        ("action_names", dataset.action_names, actions.shape[2]),
    ):
        if names is None:
            continue
        if len(names) != size:
            raise ValueError(
                f"{where}: {kind} has {len(names)} names {list(names)} for {size} "
                f"variables: give one name per variable, in order"
            )
        if len(set(names)) != len(names):
            dups = sorted({n for n in names if names.count(n) > 1})
            raise ValueError(f"{where}: {kind} repeats {dups}: every name must be unique")


def _first_bad(array: np.ndarray, names, kind: str, where: str):
    _refuse_first(
        ~np.isfinite(array),
        array,
        names,
        kind,
        where,
        "non-finite value(s) (NaN or inf)",
        "drop or repair those episodes (e.g. cut them before the gap) before using the data",
    )


def _refuse_first(bad: np.ndarray, array: np.ndarray, names, kind, where, what, fix) -> None:
    """Refuse the entries of `array` [E, T, n] where `bad`: how many, the first, and the fix."""
    if not bad.any():
        return
    e, k, i = (int(x) for x in np.argwhere(bad)[0])
    var = f"'{names[i]}'" if names is not None else f"number {i}"
    raise ValueError(
        f"{where}: the {kind}s hold {int(bad.sum())} {what}; the first "
        f"is {array[e, k, i]} at episode {e}, step {k}, {kind} {var}: {fix}"
    )


# The simulators compute in float32: a value whose square overflows it (costs, energies,
# friction laws square or multiply states) makes every prediction NaN or inf.
LARGEST = float(np.sqrt(np.finfo(np.float32).max))


def _first_huge(array: np.ndarray, names, kind: str, where: str):
    _refuse_first(
        np.abs(array) > LARGEST,
        array,
        names,
        kind,
        where,
        f"value(s) beyond {LARGEST:.1e}, which overflow the simulator's float32",
        "check the units, or drop those episodes",
    )


def _outside_control_range(dataset: Dataset, ctrl_range, where: str):
    """Refuse actions the actuator cannot apply: the simulator clips them to its control range,
    so a fit on them explains the difference with invented forces."""
    if ctrl_range is None:
        return
    low, high = np.asarray(ctrl_range, np.float64).T
    slack = 1e-6 * np.where(np.isfinite(high - low), high - low, 1.0)
    outside = (dataset.actions < low - slack) | (dataset.actions > high + slack)
    if not outside.any():
        return
    i = int(np.argwhere(outside)[0][-1])
    name = dataset.action_names[i] if dataset.action_names else f"number {i}"
    worst = float(np.abs(dataset.actions[..., i]).max())
    raise ValueError(
        f"{where}: {int(outside.sum())} of {outside.size} actions lie outside the actuator's "
        f"control range (action {name}: [{low[i]:g}, {high[i]:g}], the data reach {worst:.3g}); "
        "the simulator clips them: check the actions' units and scale, or clip them to the "
        "range if the actuator saturated"
    )


def split_episodes(n_episodes: int, fraction: float, seed: int, what: str = "splitting"):
    """(kept, held-out) episode indices: a seeded shuffle, `fraction` of the episodes held out
    and at least one on each side (models are validated, and discovery judged, by episode)."""
    if n_episodes < 2:
        raise ValueError(
            f"{what} needs at least 2 episodes (one is held out by episode); got {n_episodes}: "
            "record more episodes, or split a long record into episodes"
        )
    order = np.random.default_rng(seed).permutation(n_episodes)
    n_held = min(n_episodes - 1, max(1, round(fraction * n_episodes)))
    return np.sort(order[n_held:]), np.sort(order[:n_held])


def validate(dataset: Dataset, sim, where: str = "dataset") -> Dataset:
    """Check a dataset against a system: `sim` is an hds.envs.system.Simulator or anything with
    obs_names, action_names and timestep (physics step, s). Returns the dataset; raises a
    ValueError that names the problem and the fix."""
    check(dataset, where)
    obs_names, action_names = tuple(sim.obs_names), tuple(sim.action_names)
    for kind, got, names in (
        ("observed variables", dataset.n_obs, obs_names),
        ("actions", dataset.n_act, action_names),
    ):
        if got != len(names):
            raise ValueError(
                f"{where} has {got} {kind} per step, and this system needs "
                f"{len(names)}: {list(names)}, in this order"
            )
    for kind, got, names in (
        ("obs_names", dataset.obs_names, obs_names),
        ("action_names", dataset.action_names, action_names),
    ):
        if got is None or got == names:
            continue
        if sorted(got) == sorted(names):
            raise ValueError(
                f"{where}: {kind} {list(got)} are this system's, in another order: "
                f"reorder the variables (columns) to {list(names)}"
            )
        wrong = [g for g in got if g not in names]
        raise ValueError(
            f"{where}: {kind} {list(got)} do not match this system's {list(names)} "
            f"(unknown: {wrong}): rename them, in this order"
        )
    _first_bad(dataset.obs, dataset.obs_names, "observation", where)
    _first_bad(dataset.actions, dataset.action_names, "action", where)
    _first_huge(dataset.obs, dataset.obs_names, "observation", where)
    _first_huge(dataset.actions, dataset.action_names, "action", where)
    _outside_control_range(dataset, getattr(sim, "ctrl_range", None), where)
    timestep = float(sim.timestep)
    ratio = dataset.dt / timestep
    frames = round(ratio)
    if frames < 1 or abs(ratio - frames) > DT_RTOL * max(1.0, ratio):
        raise ValueError(
            f"{where}: dt = {dataset.dt} s is not an integer multiple of the model's physics "
            f"timestep {timestep} s (dt / timestep = {ratio:.6g}): resample the data to a multiple "
            f"of {timestep} s, or set the model's timestep (env.timestep) to divide {dataset.dt} s"
        )
    return dataset


# ---------------------------------------------------------------------------------------------
# files


def save(dataset: Dataset, path: str | os.PathLike) -> Path:
    """Write a dataset to .npz or .csv (by extension), atomically. Returns the path."""
    path = Path(path)
    suffix = _suffix(path)
    check(dataset, f"dataset to write to {path}")
    if suffix == ".npz":
        arrays = {"obs": dataset.obs, "actions": dataset.actions, "dt": np.float64(dataset.dt)}
        if dataset.obs_names is not None:
            arrays["obs_names"] = np.array(dataset.obs_names, dtype=str)
        if dataset.action_names is not None:
            arrays["action_names"] = np.array(dataset.action_names, dtype=str)
        with _atomic(path, "wb") as f:
            np.savez_compressed(f, **arrays)
    else:
        text = _csv_text(dataset)
        with _atomic(path, "w") as f:
            f.write(text)
    return path


def load(path: str | os.PathLike) -> Dataset:
    """Read a dataset from .npz or .csv (by extension). Malformed files raise a ValueError."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{path} is a directory: give a dataset file ({', '.join(FORMATS)})")
    suffix = _suffix(path)
    if not path.is_file():
        raise FileNotFoundError(f"no dataset file at {path}")
    if path.stat().st_size == 0:
        raise ValueError(
            f"{path} is empty (0 bytes): it was not written, or written and cut off; write it again"
        )
    dataset = _load_npz(path) if suffix == ".npz" else _load_csv(path)
    check(dataset, str(path))
    return dataset


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"{path}: unknown dataset format '{suffix}'; use one of {list(FORMATS)}")
    return suffix


@contextlib.contextmanager
def _atomic(path: Path, mode: str):
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        kwargs = {"newline": "", "encoding": "utf-8"} if "b" not in mode else {}
        with os.fdopen(fd, mode, **kwargs) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, file_mode())  # mkstemp makes it private; give it a normal file's mode
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _load_npz(path: Path) -> Dataset:
    def corrupt(err):
        return ValueError(
            f"{path} is not a readable .npz archive (truncated or corrupt: "
            f"{type(err).__name__}: {err}); write it again from the source data"
        )

    with open(path, "rb") as f:
        magic = f.read(4)
    if magic not in (b"PK\x03\x04", b"PK\x05\x06"):  # np.load would try other formats
        raise corrupt(ValueError(f"it does not start as a zip archive: {magic!r}"))
    try:
        with np.load(path, allow_pickle=False) as z:
            keys = sorted(z.files)
            arrays = {
                k: z[k] for k in ("obs", "actions", "dt", "obs_names", "action_names") if k in keys
            }
    except ValueError as err:
        if "allow_pickle" in str(err):
            raise ValueError(
                f"{path} holds Python objects (pickled arrays), which are not "
                "read, for safety: store plain float arrays and str arrays of "
                "names"
            ) from None
        raise corrupt(err) from None
    except Exception as err:  # zipfile, zlib, EOF, header errors: all mean a damaged file
        raise corrupt(err) from None
    missing = [k for k in ("obs", "actions", "dt") if k not in arrays]
    if missing:
        raise ValueError(
            f"{path} lacks the key(s) {missing}: a dataset .npz holds obs "
            "[E, T+1, n_obs], actions [E, T, n_act] and dt (seconds), with optional "
            f"obs_names and action_names; it has {keys}"
        )
    for key in ("obs", "actions", "dt"):
        if not np.issubdtype(arrays[key].dtype, np.number) or np.iscomplexobj(arrays[key]):
            raise ValueError(
                f"{path}: '{key}' has dtype {arrays[key].dtype}; it must hold real numbers"
            )
    if arrays["dt"].size != 1:
        raise ValueError(
            f"{path}: dt has shape {arrays['dt'].shape}; it must be one number "
            "(seconds between observations)"
        )
    names = {}
    for key in ("obs_names", "action_names"):
        if key in arrays:
            value = arrays[key]
            if value.dtype.kind not in "US" or value.ndim != 1:
                raise ValueError(
                    f"{path}: '{key}' must be a 1-D array of str, not {value.dtype} {value.shape}"
                )
            names[key] = tuple(str(n) for n in value)
    return Dataset(arrays["obs"], arrays["actions"], float(arrays["dt"].reshape(())), **names)


def _csv_text(dataset: Dataset) -> str:
    obs_names = dataset.obs_names or tuple(f"{OBS_PLACEHOLDER}{i}" for i in range(dataset.n_obs))
    action_names = dataset.action_names or tuple(str(i) for i in range(dataset.n_act))
    for name in obs_names:
        if name.startswith(ACTION_PREFIX) or name in ("episode", "t"):
            raise ValueError(
                f"observation name '{name}' cannot be a CSV column: names starting "
                f"with '{ACTION_PREFIX}' mark actions, and episode and t are taken; "
                "rename it"
            )
    header = ["episode", "t", *obs_names, *(ACTION_PREFIX + n for n in action_names)]
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    horizon = dataset.horizon
    blank = [""] * dataset.n_act
    for e in range(dataset.n_episodes):
        for k in range(horizon + 1):
            acts = [repr(float(x)) for x in dataset.actions[e, k]] if k < horizon else blank
            writer.writerow(
                [str(e), repr(k * dataset.dt), *(repr(float(x)) for x in dataset.obs[e, k]), *acts]
            )
    return out.getvalue()


def _load_csv(path: Path) -> Dataset:
    rows, lines = [], []  # the non-blank rows, and the line where each ends (1-based)
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            for row in reader:
                if row:  # a blank line (e.g. at the end) carries nothing
                    rows.append(row)
                    lines.append(reader.line_num)
    except (UnicodeDecodeError, csv.Error) as err:
        raise ValueError(
            f"{path} is not a readable CSV text file ({err}): write it again as "
            "UTF-8 comma separated text"
        ) from None
    if not rows:
        raise ValueError(f"{path} is empty: it has no header and no rows")
    header = [h.strip() for h in rows[0]]
    if header[:2] != ["episode", "t"]:
        raise ValueError(
            f"{path}: the header starts with {header[:2]}; a dataset CSV starts with "
            "the columns episode,t then the observation and u_-prefixed action "
            "columns"
        )
    is_action = [h.startswith(ACTION_PREFIX) for h in header[2:]]
    n_obs = is_action.index(True) if True in is_action else len(is_action)
    n_act = len(is_action) - n_obs
    if n_act == 0:
        raise ValueError(
            f"{path}: no action column: name each action column '{ACTION_PREFIX}"
            f"<actuator>' (e.g. {ACTION_PREFIX}slide), after the observations"
        )
    if not all(is_action[n_obs:]):
        late = [h for h, a in zip(header[2 + n_obs :], is_action[n_obs:], strict=True) if not a]
        raise ValueError(
            f"{path}: observation column(s) {late} come after action columns: put "
            f"every observation column before the {ACTION_PREFIX}-prefixed actions"
        )
    if n_obs == 0:
        raise ValueError(f"{path}: no observation column between t and the action columns")
    data = rows[1:]
    if not data:
        raise ValueError(f"{path} has a header and no data rows: it is empty")
    width = len(header)
    for row, line in zip(data, lines[1:], strict=True):
        if len(row) != width:
            raise ValueError(
                f"{path}, line {line}: {len(row)} fields where the header has "
                f"{width} (ragged row: the file is truncated or corrupt); every row "
                "needs every column, with the action cells of an episode's last row "
                "left empty"
            )
    cells = np.array(data, dtype=str)
    episode_ids = np.char.strip(cells[:, 0])
    starts = np.flatnonzero(np.r_[True, episode_ids[1:] != episode_ids[:-1]])
    bounds = np.r_[starts, len(data)]
    labels = episode_ids[starts]
    if len(set(labels.tolist())) != len(labels):
        again = next(lab for i, lab in enumerate(labels) if lab in labels[:i])
        raise ValueError(
            f"{path}: the rows of episode '{again}' are not consecutive: sort the "
            "file by episode, then t"
        )
    lengths = np.diff(bounds)
    if (lengths != lengths[0]).any():
        e = int(np.flatnonzero(lengths != lengths[0])[0])
        raise ValueError(
            f"{path}: episode '{labels[e]}' has {lengths[e]} rows and episode "
            f"'{labels[0]}' {lengths[0]}: every episode needs the same number of "
            "rows (T+1); cut them to a common length (a truncated file ends short)"
        )
    rows_per = int(lengths[0])
    if rows_per < 2:
        raise ValueError(
            f"{path}: episodes have a single row; an episode needs at least two "
            "observations (T+1 >= 2 rows)"
        )
    values = np.char.strip(cells[:, 1:])
    empty = values == ""
    last = np.zeros(len(data), dtype=bool)
    last[bounds[1:] - 1] = True
    act_empty = empty[:, 1 + n_obs :]
    if (~act_empty[last]).any():
        r = int(np.flatnonzero(last & ~act_empty.all(1))[0])
        raise ValueError(
            f"{path}, line {lines[r + 1]}: the last row of episode "
            f"'{episode_ids[r]}' has action values; the last row of an episode holds "
            "its final observation, with no action after it: leave its action cells "
            "empty (or drop the action logged after the last observation)"
        )
    empty[last, 1 + n_obs :] = False
    if empty.any():
        r, c = (int(x) for x in np.argwhere(empty)[0])
        raise ValueError(
            f"{path}, line {lines[r + 1]}: column '{header[c + 1]}' is empty; only "
            "the action cells of an episode's last row may be empty (write nan for "
            "a missing measurement)"
        )
    values = np.where(last[:, None] & (np.arange(values.shape[1]) > n_obs), "nan", values)
    try:
        numbers = values.astype(np.float64)
    except ValueError:
        for r, row in enumerate(values):
            for c, cell in enumerate(row):
                try:
                    float(cell)
                except ValueError:
                    raise ValueError(
                        f"{path}, line {lines[r + 1]}: column '{header[c + 1]}' "
                        f"holds '{cell}', which is not a number"
                    ) from None
        raise
    n_ep = len(labels)
    numbers = numbers.reshape(n_ep, rows_per, -1)
    t = numbers[:, :, 0]
    dt = float(t[0, 1] - t[0, 0])
    steps = np.diff(t, axis=1)
    if not np.isfinite(t).all() or not dt > 0:
        raise ValueError(
            f"{path}: t must be finite and increase within each episode; the first "
            f"episode's first step is {dt} s"
        )
    tol = DT_RTOL * dt + 8 * np.finfo(float).eps * float(np.abs(t).max())
    uneven = np.abs(steps - dt) > tol
    if uneven.any():
        e, k = (int(x) for x in np.argwhere(uneven)[0])
        raise ValueError(
            f"{path}: t is not evenly spaced: episode '{labels[e]}' steps "
            f"{steps[e, k]} s from t = {t[e, k]}, and the first step is {dt} s; "
            "resample the data to a fixed step (and sort each episode by t)"
        )
    obs_names = tuple(header[2 : 2 + n_obs])
    action_names = tuple(h[len(ACTION_PREFIX) :] for h in header[2 + n_obs :])
    if obs_names == tuple(f"{OBS_PLACEHOLDER}{i}" for i in range(n_obs)):
        obs_names = None
    if action_names == tuple(str(i) for i in range(n_act)):
        action_names = None
    return Dataset(
        numbers[:, :, 1 : 1 + n_obs], numbers[:, :-1, 1 + n_obs :], dt, obs_names, action_names
    )
