"""Lab plants (hds.real.lab, hds.effects.lab): seeded draws of robots that differ from their
model in many ways at once, some outside discovery's library.

A draw is reproducible from its seed and from its truth file, draws differ within the
documented bounds, each out-of-library law on the C MuJoCo plant agrees with its replica (the
oracle's simulator) where the effect itself is large, and a run on a lab plant writes the
draw's truth beside its results.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import make_config

from hds.effects.lab import LAB_EFFECTS
from hds.effects.library import candidate_effects
from hds.envs import make_env
from hds.real import lab, make_plant
from hds.real.brax_plant import BraxPlant
from hds.real.mujoco_plant import MujocoPlant
from hds.utils.io import atomic_write_json, read_json

FAMILIES = {"lab_cartpole": "env.backend=analytic", "lab_furuta": "env=furuta_balance"}
T = 15  # environment steps: 0.6 s of the cart-pole, 0.3 s of the Furuta


def effect(name, target, **params):
    return {"name": name, "target": target, "params": params}


def rollout(plant, q0, qd0, u):
    """(true states [B, T+1, nq+nv], observations [B, T+1, n_obs]) under open-loop u."""
    obs, states = [plant.reset(q0, qd0)], [np.concatenate(plant.state(), 1)]
    for t in range(u.shape[1]):
        obs.append(plant.step(u[:, t]))
        states.append(np.concatenate(plant.state(), 1))
    return np.stack(states, 1), np.stack(obs, 1)


def hanging(batch, speeds=None):
    """Pendulums hanging still (stable), the first joint at rest or at the given speeds."""
    q0 = np.tile([0.0, np.pi], (batch, 1))
    qd0 = np.zeros((batch, 2))
    if speeds is not None:
        qd0[:, 0] = speeds
    return q0, qd0


@pytest.fixture(scope="module")
def cartpole():
    return make_config("real=none", "env.backend=analytic").env


@pytest.fixture(scope="module")
def furuta():
    return make_config("real=none", "env=furuta_balance").env


# The draws -----------------------------------------------------------------------------------


@pytest.mark.parametrize("family", FAMILIES)
def test_a_draw_is_reproducible_from_its_seed_and_its_truth_file(family, tmp_path):
    truth = lab.draw(family, 4)
    assert truth == lab.draw(family, 4)
    path = atomic_write_json(tmp_path / "truth.json", truth)
    assert read_json(path) == truth
    cfg = make_config(f"real={family}", "real.draw=4", FAMILIES[family])
    assert [dataclasses.asdict(e) for e in cfg.real.effects] == truth["effects"]
    assert cfg.real.label() == f"{family}#4"
    # the plant built from the file is the plant of the config, noise included
    q0, qd0 = hanging(3, [0.3, -0.2, 0.0])
    u = np.random.default_rng(0).uniform(-0.5, 0.5, (3, T, 1))
    from_cfg = rollout(make_plant(cfg.real, cfg.env), q0, qd0, u)
    from_file = rollout(MujocoPlant(cfg.env, read_json(path)["effects"]), q0, qd0, u)
    for a, b in zip(from_cfg, from_file, strict=True):
        np.testing.assert_array_equal(a, b)
    # replacing a field rebuilds the config without drawing its effects twice
    assert len(dataclasses.replace(cfg.real, friction_gap=1.0).effects) == len(truth["effects"])


def test_a_plant_restored_to_its_noise_state_measures_what_the_uninterrupted_one_does(
    tmp_path,
):
    """What a loop that resumes past a recorded round does (hds.loop.run_loop): a fresh plant,
    its noise state set from the JSON the recording left, measures the noise the plant that
    made the recording measures next; without it, other noise."""
    cfg = make_config("real=lab_cartpole", "real.draw=2", FAMILIES["lab_cartpole"])
    q0, qd0 = hanging(4, [0.3, -0.2, 0.0, 0.1])
    u = np.random.default_rng(0).uniform(-0.5, 0.5, (4, T, 1))
    plant = make_plant(cfg.real, cfg.env)
    rollout(plant, q0, qd0, u)  # the recording
    path = atomic_write_json(tmp_path / "excitation.json", {"plant_noise": plant.noise_state()})
    _, measured = rollout(plant, q0, qd0, u)  # the evaluation after it
    resumed = make_plant(cfg.real, cfg.env)  # a new process
    _, fresh = rollout(resumed, q0, qd0, u)
    assert not np.array_equal(fresh, measured)
    resumed.set_noise_state(read_json(path)["plant_noise"])
    np.testing.assert_array_equal(rollout(resumed, q0, qd0, u)[1], measured)
    assert (
        plant.noise_state()
        and make_plant(make_config("real=brax").real, cfg.env).noise_state() == {}
    )


@pytest.mark.parametrize("family", FAMILIES)
def test_draws_differ_within_the_documented_bounds(family):
    draws = [lab.draw(family, k) for k in range(10)]
    for truth in draws:
        assert lab.in_bounds(family, truth) == []
        for e in truth["effects"]:
            p = e["params"]
            if e["name"] in ("mass_scale", "com_scale", "inertia_scale", "actuator_gain"):
                assert 0.9 <= next(iter(p.values())) <= 1.1, e  # off by up to 10%
            if e["name"] == "stribeck_friction":
                assert p["static"] > p["force"] > 0 and p["velocity"] > 0, e
    keys = draws[0]["values"]
    for key in keys:
        seen = [d["values"][key] for d in draws]
        if key.startswith("action_delay"):
            assert set(seen) == {0, 1}  # both lengths occur
        elif key.startswith("cogging_torque") and key.endswith("periods"):
            assert len(set(seen)) > 3
        elif not key.startswith("encoder_quantization"):  # a fixed 2,048 counts a turn
            assert len(set(seen)) == len(seen), key
    # every joint has friction; the out-of-library laws are no candidates of discovery's
    truth = draws[0]
    frictions = {e["target"] for e in truth["effects"] if e["name"] == "stribeck_friction"}
    viscous = {e["target"] for e in truth["effects"] if e["name"] == "viscous_damping"}
    joints = {"lab_cartpole": {"slider", "hinge"}, "lab_furuta": {"arm", "pendulum"}}[family]
    assert frictions == viscous == joints
    outside = {
        "lab_cartpole": {"backlash@slide", "patch_friction@slider"},
        "lab_furuta": {"cogging_torque@arm"},
    }[family]
    assert outside <= set(truth["out_of_library"])
    assert not {e.name for e in LAB_EFFECTS} & set(candidate_effects())


def test_a_lab_plant_refuses_another_system_and_a_bad_draw():
    with pytest.raises(ValueError, match="lab_furuta is a plant of furuta.xml.*env=furuta"):
        make_config("real=lab_furuta")
    with pytest.raises(ValueError, match="no lab family; choose one of"):
        make_config("real=lab_cartpole", "real.family=lab_robot")
    with pytest.raises(ValueError, match="real.draw = -1 must be a whole number"):
        make_config("real=lab_cartpole", "real.draw=-1")
    with pytest.raises(ValueError, match="discover.effects"):
        make_config("real=lab_cartpole", "simulator=corrected", "discover.effects=[backlash]")


# Each out-of-library law on the plant against its replica --------------------------------------


def test_cogging_on_the_plant_matches_its_replica(furuta):
    """The law is the same in both (a torque from the arm's angle at every physics step): the
    plant and its replica agree to the engines' own agreement, far below the effect."""
    cogging = [effect("cogging_torque", "arm", amplitude=5e-4, periods=18, phase=0.3)]
    q0, qd0 = hanging(2)
    u = np.zeros((2, T, 1))
    u[0], u[1] = 0.2, -0.1  # 1e-3 and -5e-4 N m: the arm turns through several periods
    plant, _ = rollout(MujocoPlant(furuta, cogging), q0, qd0, u)
    replica, _ = rollout(BraxPlant(make_env(furuta, effects=cogging, sharpness=None)), q0, qd0, u)
    nominal, _ = rollout(MujocoPlant(furuta), q0, qd0, u)
    effect_size = np.abs(plant - nominal).max(axis=(0, 1))
    assert np.all(effect_size[[0, 2]] > 3e-3)  # the arm's angle and speed
    assert np.all(np.abs(plant - replica).max(axis=(0, 1)) < 0.01 * effect_size)


def test_backlash_on_the_plant_matches_its_replica(cartpole):
    """A control that reverses every few steps: after each reversal the drive crosses the gap
    and the cart gets nothing; the replica is the same discrete law (exact and smoothed
    simulators alike) and agrees with the plant to the engines' own agreement."""
    backlash = [effect("backlash", "slide", gap=0.004, inertia=0.008)]
    q0, qd0 = hanging(2)
    u = np.zeros((2, T, 1))
    u[0, :, 0] = np.where((np.arange(T) // 3) % 2 == 0, 0.3, -0.3)
    u[1, :, 0] = np.where((np.arange(T) // 2) % 2 == 0, 0.05, -0.05)
    plant, _ = rollout(MujocoPlant(cartpole, backlash), q0, qd0, u)
    replica, _ = rollout(BraxPlant(make_env(cartpole, effects=backlash)), q0, qd0, u)
    nominal, _ = rollout(MujocoPlant(cartpole), q0, qd0, u)
    effect_size = np.abs(plant - nominal).max(axis=(0, 1))
    assert np.all(effect_size > 5e-4)
    assert np.all(np.abs(plant - replica).max(axis=(0, 1)) < 0.01 * effect_size)
    # the cart lags the nominal one: every reversal costs it a crossing without force
    assert np.all(np.abs(plant[:, 1:, 2]).sum(1) < np.abs(nominal[:, 1:, 2]).sum(1))


def test_friction_varying_along_the_rail_on_the_plant_matches_its_replica(cartpole):
    """A rough patch of the rail: carts that slide across it lose speed there, on the plant
    (MuJoCo's frictionloss set from the cart's position at every physics step) as on the
    replica (the same force, smoothed at rest only), to well under 1% of the effect; a cart
    that runs away from the patch feels nothing of it."""
    patch = [effect("patch_friction", "slider", force=8.0, center=0.15, width=0.1)]
    q0, qd0 = hanging(4, [0.8, 0.4, -0.3, -0.3])
    q0[2, 0], q0[3, 0] = 0.3, -0.5  # back across the patch; away from it
    u = np.zeros((4, T, 1))
    u[2] = -0.02  # 2 N towards the patch: short of holding the cart against 8 N
    plant, _ = rollout(MujocoPlant(cartpole, patch), q0, qd0, u)
    replica, _ = rollout(BraxPlant(make_env(cartpole, effects=patch)), q0, qd0, u)
    nominal, _ = rollout(MujocoPlant(cartpole), q0, qd0, u)
    crossing = slice(0, 3)
    effect_size = np.abs(plant - nominal)[crossing].max(axis=(0, 1))
    assert np.all(effect_size[[0, 2]] > 0.03)  # the cart's position and speed
    assert np.all(np.abs(plant - replica)[crossing].max(axis=(0, 1)) < 0.01 * effect_size)
    # the friction slows the cart: it ends slower than the nominal one, where it varies
    assert np.all(np.abs(plant[crossing, -1, 2]) < np.abs(nominal[crossing, -1, 2]))
    np.testing.assert_allclose(plant[3], nominal[3], atol=1e-9)


def test_stribeck_friction_on_the_plant_and_its_replica(cartpole):
    """A push between the sliding and the static friction holds the plant's cart where
    Coulomb friction at the sliding level lets it go, and the replica (smoothed, the oracle's)
    holds it too, short of the plant by its tanh law's creep; coasting to rest, the replica
    follows the plant closer than Coulomb friction does."""
    stribeck = [effect("stribeck_friction", "slider", force=10.0, static=16.0, velocity=0.05)]
    coulomb = [effect("coulomb_friction", "slider", force=10.0)]
    q0, qd0 = hanging(2, [0.15, 0.0])
    u = np.zeros((2, T, 1))
    u[1] = 0.13  # 13 N: above 10 N of sliding friction, below 16 N of static
    plant, _ = rollout(MujocoPlant(cartpole, stribeck), q0, qd0, u)
    replica, _ = rollout(BraxPlant(make_env(cartpole, effects=stribeck)), q0, qd0, u)
    sliding, _ = rollout(MujocoPlant(cartpole, coulomb), q0, qd0, u)
    pushed = 1
    assert abs(plant[pushed, -1, 0]) < 0.005  # MuJoCo's soft frictionloss creeps a little
    assert sliding[pushed, -1, 0] > 0.03
    assert replica[pushed, -1, 0] < 0.5 * sliding[pushed, -1, 0]
    coasting = 0
    to_replica = np.abs(plant[coasting] - replica[coasting]).max(0)
    to_coulomb = np.abs(plant[coasting] - sliding[coasting]).max(0)
    speed = 2  # the cart's: the static peak brakes it harder in the last steps before rest
    assert to_coulomb[speed] > 5e-3 and to_replica[speed] < 0.5 * to_coulomb[speed]


@pytest.mark.parametrize("family", FAMILIES)
def test_a_draws_plant_tracks_its_replica(family):
    """Everything of a draw at once, pendulum hanging (a falling one would amplify any
    difference), coasting, pushed and shaken: the oracle's simulator ends far closer to the
    plant than the nominal model does."""
    cfg = make_config(f"real={family}", "real.draw=1", FAMILIES[family])
    plant = make_plant(cfg.real, cfg.env)
    top = plant.ctrl_range[0, 1]
    q0, qd0 = hanging(3, np.array([0.5, 0.0, 0.0]) * (4 if family == "lab_furuta" else 1))
    u = np.zeros((3, T, 1))
    u[1] = 0.2 * top
    u[2, :, 0] = np.where((np.arange(T) // 3) % 2 == 0, 0.2, -0.2) * top
    states, obs = rollout(plant, q0, qd0, u)
    replica, _ = rollout(BraxPlant(make_env(cfg.env, effects=list(cfg.real.effects))), q0, qd0, u)
    nominal, _ = rollout(MujocoPlant(cfg.env), q0, qd0, u)
    to_replica = np.abs(states - replica)[:, -1].max(0)
    to_nominal = np.abs(states - nominal)[:, -1].max(0)
    assert np.all(to_replica < 0.2 * to_nominal), (to_replica, to_nominal)
    # what is measured: positions on the encoders' grid, velocities noisy
    step = 2 * np.pi / lab.COUNTS
    np.testing.assert_allclose(obs[..., 1] / step, np.round(obs[..., 1] / step), atol=1e-6)
    assert np.all(np.abs(obs[..., 1] - states[..., 1]) <= step / 2 + 1e-9)
    assert np.abs(obs[..., 3] - states[..., 3]).std() > 0.005


# A run ---------------------------------------------------------------------------------------


def test_a_run_on_a_lab_plant_writes_the_draws_truth(tmp_path):
    """PODS on the nominal simulator, evaluated on draw 2 of the lab cart-pole (tiny budgets):
    the rows name the draw and truth.json beside summary.json is the draw's truth."""
    import hds

    cfg = make_config("real=lab_cartpole", "real.draw=2", "debug=fast", "eval_episodes=4")
    result = hds.train(cfg, out_dir=tmp_path)
    assert read_json(tmp_path / "truth.json") == lab.draw("lab_cartpole", 2)
    assert [row["plant"] for row in result.rows] == ["lab_cartpole#2"]
    assert np.isfinite(result.rows[0]["real_return"])
    applied = {
        f"{e['name']}@{e['target']}"
        for e in read_json(tmp_path / "summary.json")["real"]["effects"]
    }
    assert {"backlash@slide", "stribeck_friction@slider"} <= applied


@pytest.mark.slow
def test_the_oracle_trains_on_a_lab_draws_replica(tmp_path):
    """method=oracle on a lab draw: it trains on the simulator carrying the draw's effects
    (their replicas, ramped in by the continuation, the saturation at its value throughout)
    and is evaluated on the plant."""
    import hds

    cfg = make_config(
        "real=lab_cartpole", "real.draw=2", "debug=fast", "method=oracle", "eval_episodes=4"
    )
    result = hds.train(cfg, out_dir=tmp_path)
    row = result.rows[0]
    assert row["method"] == "oracle" and row["plant"] == "lab_cartpole#2"
    assert np.isfinite(row["sim_return"]) and np.isfinite(row["real_return"])
    assert (tmp_path / "truth.json").is_file()


def test_the_docs_state_every_drawn_value():
    from conftest import ROOT

    text = (ROOT / "docs" / "lab-plants.md").read_text()
    missing = [
        d.key for _, table in lab.FAMILIES.values() for d in table if f"`{d.key}`" not in text
    ]
    assert not missing, f"docs/lab-plants.md lacks {missing}"
