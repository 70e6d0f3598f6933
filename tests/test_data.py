"""hds.data: the dataset format (round trips, every malformed case), excitation signals, and
recording from a plant. One brax compile (the BraxPlant's step), shared by the module."""

from __future__ import annotations

import os

import jax
import numpy as np
import pytest

from hds.data import (
    Dataset,
    chirp,
    collect,
    excitation,
    initial_states,
    load,
    prbs,
    random_steps,
    save,
    validate,
)
from hds.utils.io import file_mode

OBS = ("q_slider", "q_hinge", "qd_slider", "qd_hinge")
ACT = ("slide",)
E, T = 3, 20


def make_dataset(n_ep=E, horizon=T, dt=0.04, names=True, seed=0) -> Dataset:
    rng = np.random.default_rng(seed)
    magnitude = 10.0 ** rng.integers(-8, 8, size=(1, 1, len(OBS)))  # tiny to huge values
    obs = rng.normal(size=(n_ep, horizon + 1, len(OBS))) * magnitude
    actions = rng.uniform(-3, 3, size=(n_ep, horizon, len(ACT)))
    return Dataset(obs, actions, dt, OBS if names else None, ACT if names else None)


def assert_same(a: Dataset, b: Dataset):
    assert a.obs.dtype == b.obs.dtype == np.float64
    np.testing.assert_array_equal(a.obs, b.obs)
    np.testing.assert_array_equal(a.actions, b.actions)
    assert a.dt == b.dt
    assert a.obs_names == b.obs_names and a.action_names == b.action_names


@pytest.fixture(scope="module")
def sim(cartpole_env):
    return cartpole_env.sim


# ------------------------------------------------------------------------------ round trips


@pytest.mark.parametrize("ext", ["npz", "csv"])
@pytest.mark.parametrize("names", [True, False])
def test_round_trip_is_exact(tmp_path, ext, names):
    data = make_dataset(names=names)
    data.obs[0, 3, 1] = 1 / 3  # not a short decimal
    data.actions[2, 0, 0] = -0.0
    path = save(data, tmp_path / f"d.{ext}")
    back = load(path)
    assert_same(data, back)
    assert np.signbit(back.actions[2, 0, 0])
    assert sorted(os.listdir(tmp_path)) == [f"d.{ext}"]  # no temporary left behind
    assert path.stat().st_mode & 0o777 == file_mode()  # readable like any new file


def test_csv_layout_follows_the_contract(tmp_path):
    data = make_dataset(n_ep=2, horizon=2, dt=0.5)
    lines = save(data, tmp_path / "d.csv").read_text().splitlines()
    assert lines[0] == "episode,t,q_slider,q_hinge,qd_slider,qd_hinge,u_slide"
    assert len(lines) == 1 + 2 * 3  # T+1 rows per episode
    rows = [line.split(",") for line in lines[1:]]
    assert [r[:2] for r in rows] == [
        ["0", "0.0"],
        ["0", "0.5"],
        ["0", "1.0"],
        ["1", "0.0"],
        ["1", "0.5"],
        ["1", "1.0"],
    ]
    assert [r[-1] == "" for r in rows] == [False, False, True] * 2  # last row: no action
    assert float(rows[1][-1]) == data.actions[0, 1, 0]


def test_csv_from_a_logger_reads(tmp_path):
    """A hand-written file: string episode labels, t not from zero, spaces, a trailing newline."""
    text = (
        "episode,t,q_slider,q_hinge,qd_slider,qd_hinge,u_slide\n"
        "run_a, 10.00, 0, 0.1, 0, 0, 1.5\n"
        "run_a, 10.04, 0, 0.2, 0, 0, -1\n"
        "run_a, 10.08, 0, 0.3, 0, 0,\n"
        "run_b, 0.00, 1, 0.1, 0, 0, 0\n"
        "run_b, 0.04, 1, 0.2, 0, 0, 2\n"
        "run_b, 0.08, 1, nan, 0, 0,\n\n"
    )
    (tmp_path / "log.csv").write_text(text)
    data = load(tmp_path / "log.csv")
    assert data.obs.shape == (2, 3, 4) and data.actions.shape == (2, 2, 1)
    assert data.dt == pytest.approx(0.04)
    np.testing.assert_array_equal(data.actions[:, :, 0], [[1.5, -1], [0, 2]])
    assert (data.obs_names, data.action_names) == (OBS, ACT)
    assert np.isnan(data.obs[1, 2, 1])


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    path = save(make_dataset(seed=1), tmp_path / "d.npz")
    before = path.read_bytes()

    def crash(file, **arrays):
        file.write(b"PK partial")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez_compressed", crash)
    with pytest.raises(OSError, match="disk full"):
        save(make_dataset(seed=2), path)
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["d.npz"]
    with pytest.raises(ValueError, match="off-by-one"):  # an invalid dataset is never written
        save(Dataset(np.zeros((1, 3, 4)), np.zeros((1, 3, 1)), 0.04), tmp_path / "bad.csv")
    assert os.listdir(tmp_path) == ["d.npz"]


# ------------------------------------------------------------------------------ validate


def test_valid_data_validates(sim):
    assert sim.timestep == pytest.approx(0.02) and sim.dt == pytest.approx(0.04)
    for dt in (sim.timestep, sim.dt, 2 * sim.dt, 0.04 * (1 + 1e-9), 0.1):
        validate(make_dataset(dt=dt), sim)
    validate(make_dataset(names=False), sim)  # no names: only sizes are checked


def _bad(**changes):
    data = make_dataset()
    for key, value in changes.items():
        setattr(data, key, value)
    return data


def _with(array, index, value):
    array = array.copy()
    array[index] = value
    return array


BASE = make_dataset()
BAD_DATASETS = {
    "obs_dims": (
        _bad(obs=BASE.obs[..., :3], obs_names=None),
        ["3 observed variables", "needs 4", "q_slider"],
    ),
    "act_dims": (
        _bad(actions=np.zeros((E, T, 2)), action_names=None),
        ["2 actions", "needs 1", "slide"],
    ),
    "obs_2d": (_bad(obs=BASE.obs[0]), ["3 dimensions", "episode axis"]),
    "act_2d": (_bad(actions=BASE.actions[..., 0]), ["[episodes, T, n_act]"]),
    "t_mismatch": (_bad(actions=np.zeros((E, T + 1, 1))), ["off-by-one", f"need {T + 2} steps"]),
    "episodes": (_bad(actions=np.zeros((E - 1, T, 1))), [f"{E} episodes", f"{E - 1}"]),
    "empty": (_bad(obs=np.zeros((0, T + 1, 4)), actions=np.zeros((0, T, 1))), ["empty"]),
    "no_step": (_bad(obs=BASE.obs[:, :1], actions=BASE.actions[:, :0]), ["empty", "T = 0"]),
    "nan_obs": (
        _bad(obs=_with(BASE.obs, (1, 5, 1), np.nan)),
        ["NaN or inf", "nan at episode 1, step 5, observation 'q_hinge'"],
    ),
    "inf_act": (
        _bad(actions=_with(BASE.actions, (2, 7, 0), -np.inf)),
        ["-inf at episode 2, step 7, action 'slide'"],
    ),
    "dt_zero": (_bad(dt=0.0), ["dt = 0.0", "positive"]),
    "dt_negative": (_bad(dt=-0.04), ["positive"]),
    "dt_nan": (_bad(dt=float("nan")), ["positive"]),
    "dt_1.5": (_bad(dt=0.03), ["not an integer multiple", "timestep 0.02 s", "1.5"]),
    "dt_small": (_bad(dt=0.01), ["not an integer multiple", "0.5"]),
    "names_wrong": (
        _bad(obs_names=("x", "theta", "x_dot", "theta_dot")),
        ["do not match", "q_slider", "'x'", "rename"],
    ),
    "names_order": (
        _bad(obs_names=("q_hinge", "q_slider", "qd_slider", "qd_hinge")),
        ["another order", "reorder"],
    ),
    "action_name": (_bad(action_names=("force",)), ["action_names", "'force'", "slide"]),
    "names_count": (_bad(obs_names=OBS[:3]), ["3 names", "4 variables"]),
    "names_dup": (_bad(obs_names=(*OBS[:3], "q_slider")), ["repeats", "q_slider"]),
}


@pytest.mark.parametrize("case", list(BAD_DATASETS))
def test_validate_names_the_problem(sim, case):
    data, fragments = BAD_DATASETS[case]
    with pytest.raises(ValueError) as err:
        validate(data, sim)
    for fragment in fragments:
        assert fragment in str(err.value), (fragment, str(err.value))


# ------------------------------------------------------------------------------ malformed files


def _csv(tmp_path, edit) -> str:
    path = save(make_dataset(n_ep=2, horizon=3, dt=0.04), tmp_path / "d.csv")
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(edit(lines)))
    return path


def _npz(tmp_path, **arrays):
    path = tmp_path / "d.npz"
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path


GOOD = {"obs": np.zeros((2, 4, 4)), "actions": np.zeros((2, 3, 1)), "dt": 0.04}


def _cut(tmp_path, fraction, ext):
    path = save(make_dataset(), tmp_path / f"d.{ext}")
    raw = path.read_bytes()
    path.write_bytes(raw[: int(len(raw) * fraction)])
    return path


def _flip(tmp_path):
    path = save(make_dataset(), tmp_path / "d.npz")
    raw = bytearray(path.read_bytes())
    mid = len(raw) // 2
    raw[mid : mid + 16] = bytes(16)
    path.write_bytes(bytes(raw))
    return path


def _write(path, raw: bytes):
    path.write_bytes(raw)
    return path


def _replace_cell(lines, line, column, value):
    cells = lines[line].rstrip("\n").split(",")
    cells[column] = value
    return [*lines[:line], ",".join(cells) + "\n", *lines[line + 1 :]]


BAD_FILES = {
    "npz_empty": (lambda p: _write(p / "d.npz", b""), ["empty (0 bytes)"]),
    "csv_empty": (lambda p: _write(p / "d.csv", b""), ["empty"]),
    "csv_blank": (lambda p: _write(p / "d.csv", b"\n\n"), ["empty"]),
    "npz_cut": (lambda p: _cut(p, 0.6, "npz"), ["truncated or corrupt"]),
    "npz_cut_early": (lambda p: _cut(p, 0.05, "npz"), ["truncated or corrupt"]),
    "npz_flipped": (_flip, ["truncated or corrupt"]),
    "npz_not_zip": (lambda p: _write(p / "d.npz", b"obs,actions\n1,2\n"), ["truncated or corrupt"]),
    "npz_missing_key": (
        lambda p: _npz(p, obs=GOOD["obs"], dt=0.04),
        ["lacks the key(s) ['actions']", "obs [E, T+1, n_obs]"],
    ),
    "npz_objects": (
        lambda p: _npz(p, **{**GOOD, "obs_names": np.array([1, "a", None], dtype=object)}),
        ["Python objects"],
    ),
    "npz_t_mismatch": (
        lambda p: _npz(p, **{**GOOD, "actions": np.zeros((2, 4, 1))}),
        ["off-by-one", "d.npz"],
    ),
    "npz_dt_shape": (lambda p: _npz(p, **{**GOOD, "dt": [0.04, 0.04]}), ["dt has shape (2,)"]),
    "npz_text_obs": (
        lambda p: _npz(p, **{**GOOD, "obs": np.full((2, 4, 4), "a")}),
        ["'obs' has dtype", "real numbers"],
    ),
    "npz_names_2d": (
        lambda p: _npz(p, **{**GOOD, "obs_names": np.array([["a", "b"]] * 2)}),
        ["'obs_names' must be a 1-D array of str"],
    ),
    "csv_cut_mid_row": (lambda p: _cut(p, 0.5, "csv"), ["ragged row", "truncated or corrupt"]),
    "csv_cut_at_row": (
        lambda p: _csv(p, lambda ls: ls[:-1]),
        ["episode '1' has 3 rows", "same number of rows"],
    ),
    "csv_ragged": (
        lambda p: _csv(p, lambda ls: [*ls[:3], ls[3].rstrip("\n") + ",7\n", *ls[4:]]),
        ["line 4", "8 fields", "header has 7"],
    ),
    "csv_header_only": (lambda p: _csv(p, lambda ls: ls[:1]), ["no data rows"]),
    "csv_no_actions": (
        lambda p: _csv(p, lambda ls: [ls[0].replace("u_slide", "slide"), *ls[1:]]),
        ["no action column", "u_"],
    ),
    "csv_obs_after_action": (
        lambda p: _csv(
            p, lambda ls: [ls[0].replace("qd_hinge,u_slide", "u_slide,qd_hinge"), *ls[1:]]
        ),
        ["['qd_hinge'] come after action columns"],
    ),
    "csv_no_t": (
        lambda p: _csv(p, lambda ls: [ls[0].replace("episode,t", "ep,time"), *ls[1:]]),
        ["starts with the columns episode,t"],
    ),
    "csv_text_cell": (
        lambda p: _csv(p, lambda ls: _replace_cell(ls, 2, 3, "1.2.3")),
        ["line 3", "column 'q_hinge'", "'1.2.3'", "not a number"],
    ),
    "csv_empty_cell": (
        lambda p: _csv(p, lambda ls: _replace_cell(ls, 2, 4, "")),
        ["line 3", "column 'qd_slider' is empty"],
    ),
    "csv_missing_action": (
        lambda p: _csv(p, lambda ls: _replace_cell(ls, 1, 6, "")),
        ["line 2", "column 'u_slide' is empty"],
    ),
    "csv_last_row_action": (
        lambda p: _csv(p, lambda ls: _replace_cell(ls, 4, 6, "0.5")),
        ["line 5", "last row of episode '0' has action values", "empty"],
    ),
    "csv_uneven_t": (
        lambda p: _csv(p, lambda ls: _replace_cell(ls, 6, 1, "0.05")),
        ["not evenly spaced", "episode '1'", "resample"],
    ),
    "csv_t_flat": (
        lambda p: _csv(p, lambda ls: _replace_cell(ls, 2, 1, "0.0")),
        ["t must be finite and increase"],
    ),
    "csv_interleaved": (
        lambda p: _csv(p, lambda ls: [ls[0], ls[1], ls[5], *ls[2:5], *ls[6:]]),
        ["episode '0' are not consecutive", "sort the file"],
    ),
    "csv_single_row": (lambda p: _csv(p, lambda ls: [ls[0], ls[4], ls[8]]), ["single row"]),
    "csv_binary": (
        lambda p: _write(p / "d.csv", b"\xff\xfe\x00\x81 not text"),
        ["not a readable CSV"],
    ),
    "extension": (lambda p: p / "d.parquet", ["unknown dataset format '.parquet'", ".npz"]),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_malformed_file_gives_a_clear_error(tmp_path, case):
    make, fragments = BAD_FILES[case]
    path = make(tmp_path)
    with pytest.raises(ValueError) as err:
        load(path)
    assert type(err.value) is ValueError  # not a numpy / zipfile exception leaking out
    for fragment in fragments:
        assert fragment in str(err.value), (fragment, str(err.value))


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="no dataset file"):
        load(tmp_path / "nothing.csv")


def test_reserved_observation_name_cannot_go_to_csv(tmp_path):
    data = make_dataset()
    data.obs_names = ("u_x", *OBS[1:])
    save(data, tmp_path / "ok.npz")  # fine in npz
    with pytest.raises(ValueError, match="mark actions"):
        save(data, tmp_path / "d.csv")
    assert os.listdir(tmp_path) == ["ok.npz"]


# ------------------------------------------------------------------------------ excitation

RANGE = np.array([[-3.0, 3.0], [0.5, 1.0]])
SIGNAL_FNS = {"steps": random_steps, "chirp": chirp, "prbs": prbs}


@pytest.mark.parametrize("kind", list(SIGNAL_FNS))
def test_signals_within_limits_and_reproducible(kind):
    fn = SIGNAL_FNS[kind]
    u = fn(7, 5, 300, 0.01, RANGE)
    assert u.shape == (5, 300, 2) and np.isfinite(u).all()
    assert (u >= RANGE[:, 0]).all() and (u <= RANGE[:, 1]).all()
    for a in range(2):  # it uses the range, not just a corner of it
        assert np.ptp(u[..., a]) > 0.5 * np.ptp(RANGE[a])
    np.testing.assert_array_equal(u, fn(7, 5, 300, 0.01, RANGE))
    np.testing.assert_array_equal(u, fn(np.random.default_rng(7), 5, 300, 0.01, RANGE))
    np.testing.assert_array_equal(u, excitation(kind, 7, 5, 300, 0.01, RANGE))
    assert not np.array_equal(u, fn(8, 5, 300, 0.01, RANGE))
    assert not np.array_equal(u[0], u[1])  # episodes differ
    key = jax.random.PRNGKey(3)
    np.testing.assert_array_equal(fn(key, 2, 50, 0.01, RANGE), fn(key, 2, 50, 0.01, RANGE))
    half = fn(7, 5, 300, 0.01, RANGE, scale=0.5)
    assert (np.abs(half - RANGE.mean(1)) <= 0.25 * np.ptp(RANGE, 1) + 1e-12).all()
    with pytest.raises(ValueError, match="no finite limits"):
        fn(0, 1, 10, 0.01, [[-np.inf, np.inf]])
    with pytest.raises(ValueError, match=r"\[n_act, 2\]"):
        fn(0, 1, 10, 0.01, [-1.0, 1.0])


def test_chirp_frequency_rises():
    dt, horizon = 0.01, 2000
    u = chirp(0, 2, horizon, dt, [[-1.0, 1.0]], f0=0.2, f1=5.0)[..., 0]
    for ep in u:
        crossings = np.flatnonzero(np.diff(np.signbit(ep).astype(int)) != 0)
        gaps = np.diff(crossings) * dt  # half periods, seconds
        assert len(crossings) > 20
        quarters = np.array_split(gaps, 4)
        means = [q.mean() for q in quarters]
        assert means == sorted(means, reverse=True)  # half period shrinks: frequency rises
        # at the end, the half period is about 1 / (2 f1)
        assert gaps[-5:].mean() == pytest.approx(1 / (2 * 5.0), rel=0.15)
    assert np.abs(u).max() == pytest.approx(1.0, abs=1e-3)
    with pytest.raises(ValueError, match="Nyquist"):
        chirp(0, 1, 10, 0.01, [[-1.0, 1.0]], f1=80.0)


def test_prbs_is_a_maximum_length_binary_sequence():
    u = prbs(1, 3, 2 * 63 * 2, 0.01, [[-2.0, 4.0]], bit_time=0.02, order=6)[..., 0]
    assert set(np.unique(u)) == {-2.0, 4.0}
    bits = u[:, ::2] > 1.0  # one bit per 2 steps
    period = 2**6 - 1
    np.testing.assert_array_equal(bits[:, :period], bits[:, period : 2 * period])
    assert (bits[:, :period].sum(1) == 2**5).all()  # m-sequence balance
    for order in (4, 5, 8, 11):  # every register length gives its maximum period
        u = prbs(0, 1, 2 * (2**order - 1), 0.01, [[-1.0, 1.0]], order=order)[0, :, 0]
        p = 2**order - 1
        np.testing.assert_array_equal(u[:p], u[p:])
        assert all(not np.array_equal(u[: p - k], u[k:p]) for k in (1, 2, 3, p // 2))
    with pytest.raises(ValueError, match="PRBS order 3 is not supported"):
        prbs(0, 1, 10, 0.01, [[-1.0, 1.0]], order=3)


def test_random_steps_hold_times():
    dt = 0.01
    u = random_steps(4, 4, 1000, dt, [[-1.0, 1.0]], min_hold=0.1, max_hold=0.3)[..., 0]
    for ep in u:
        changes = np.flatnonzero(np.diff(ep) != 0) + 1
        runs = np.diff(np.r_[0, changes])  # complete holds (the last, cut one aside)
        assert len(runs) >= 3
        assert runs.min() >= 10 and runs.max() <= 30
    with pytest.raises(ValueError, match="min_hold <= max_hold"):
        random_steps(0, 1, 10, dt, [[-1.0, 1.0]], min_hold=0.5, max_hold=0.1)


# ------------------------------------------------------------------------------ collect


@pytest.fixture(scope="module")
def plant(cartpole_env):
    from hds.real.brax_plant import BraxPlant

    return BraxPlant(cartpole_env)


@pytest.fixture(scope="module")
def starts(cartpole_env):
    return initial_states(cartpole_env.task, 0, E)


@pytest.fixture(scope="module")
def recorded(plant, cartpole_env, starts):
    u = prbs(0, E, T, plant.dt, plant.ctrl_range, scale=0.3)
    return u, collect(plant, cartpole_env.task, *starts, u)


def test_initial_states_follow_the_task(cartpole_env, starts):
    q0, qd0 = starts
    task = cartpole_env.task
    assert q0.shape == (E, 2) and qd0.shape == (E, 2)
    assert (np.abs(q0 - task.q_mean) <= task.q_spread + 1e-6).all()
    assert (np.abs(qd0) <= task.qd_spread + 1e-6).all()
    np.testing.assert_array_equal(q0, initial_states(task, jax.random.PRNGKey(0), E)[0])


def test_collect_open_loop(recorded, plant, sim, starts, tmp_path):
    u, data = recorded
    assert data.obs.shape == (E, T + 1, 4) and data.actions.shape == (E, T, 1)
    assert np.isfinite(data.obs).all()
    assert data.dt == pytest.approx(0.04) and data.obs_names == OBS and data.action_names == ACT
    np.testing.assert_array_equal(data.actions, u)
    np.testing.assert_allclose(data.obs[:, 0], np.concatenate(starts, 1), atol=1e-6)
    assert np.abs(data.obs[:, -1] - data.obs[:, 0]).max() > 1e-3  # it moved
    validate(data, sim)
    validate(load(save(data, tmp_path / "rec.csv")), sim)
    # every second observation: dt twice the env's still fits the physics timestep
    validate(Dataset(data.obs[:, ::2], data.actions[:, ::2], 2 * data.dt, OBS, ACT), sim)
    wrong = Dataset(data.obs, data.actions, 1.5 * sim.timestep, OBS, ACT)
    with pytest.raises(ValueError, match="not an integer multiple"):
        validate(wrong, sim)


def test_collect_policy_matches_open_loop_replay(recorded, plant, cartpole_env, sim, starts):
    gain = np.array([[0.5, 2.0, 0.2, 0.3]])
    data = collect(plant, cartpole_env.task, *starts, lambda obs: obs @ gain.T, horizon=T)
    assert data.obs.shape == (E, T + 1, 4) and data.actions.shape == (E, T, 1)
    np.testing.assert_allclose(data.actions[:, 3], data.obs[:, 3] @ gain.T, rtol=1e-6)
    validate(data, sim)
    replay = collect(plant, cartpole_env.task, *starts, data.actions)  # same plant: same path
    np.testing.assert_allclose(replay.obs, data.obs, rtol=1e-5, atol=1e-5)


def test_collect_rejects_bad_arguments(plant, cartpole_env, starts):
    task = cartpole_env.task
    with pytest.raises(ValueError, match=r"need \[E, T, n_act\] = \[3, 20, 1\]"):
        collect(plant, task, *starts, np.zeros((E, T, 2)))
    with pytest.raises(ValueError, match="give the horizon"):
        collect(plant, task, *starts, lambda obs: obs[:, :1])
    with pytest.raises(ValueError, match="longer than"):
        collect(plant, task, *starts, np.zeros((E, T, 1)), horizon=T + 1)


def test_active_excitation_doubles_the_amplitude_until_the_data_identify():
    """hds.data.acquire.until_identifiable: while the check names something the data so far
    cannot identify, it records again at twice the amplitude (at most the whole range), and
    its notes say why; what the full range still cannot identify is noted, not hidden."""
    from hds.data.acquire import until_identifiable

    asked = []

    def record(scale, attempt):
        asked.append((scale, attempt))
        return make_dataset(n_ep=1, seed=attempt)

    def held_until(n):  # the joint moves once n datasets are in
        return lambda data: [] if data.n_episodes >= n else ["slider never moves"]

    data, scale, notes = until_identifiable(record, held_until(3), 0.2)
    assert asked == [(0.2, 0), (0.4, 1), (0.8, 2)] and scale == 0.8 and len(data) == 3
    assert notes == [
        "slider never moves (excitation 0.2 of the half range): recorded more at 0.4",
        "slider never moves (excitation 0.4 of the half range): recorded more at 0.8",
    ]
    asked.clear()
    earlier = [make_dataset(n_ep=1, seed=9)]
    data, scale, notes = until_identifiable(record, held_until(99), 0.5, earlier)
    assert asked == [(0.5, 0), (1.0, 1)] and scale == 1.0 and data[0] is earlier[0]
    assert notes[-1] == "still not identifiable at full excitation: slider never moves"
