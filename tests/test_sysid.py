"""The hand-off of discovery's named effects to MuJoCo's own system identification
(hds.discover.sysid, mujoco.sysid) and EMPS's reference identification (IDIM-LS,
hds.data.emps.idim_ls). Cheap: C MuJoCo and numpy only, nothing compiles with JAX.

The cart-pole's "measured" data comes from C MuJoCo itself (the MJCF with the hidden effects
written natively), so a fit in MuJoCo's own laws can recover them exactly."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
from conftest import SHARED, make_config

from hds.data import Dataset, random_steps
from hds.discover import NamedEffect
from hds.discover.sysid import load_handoff, model_sequences, sysid_module, write_handoff
from hds.real.mujoco_plant import mujoco_spec

EMPS = SHARED / "data" / "emps"


def named(name: str, target: str, **params) -> NamedEffect:
    return NamedEffect(name, target, params, {}, {}, 0.0)


def hidden(name: str, target: str, **params) -> dict:
    return {"name": name, "target": target, "params": params}


@pytest.fixture(scope="module")
def sysid():
    return sysid_module()


@pytest.fixture(scope="module")
def env_cfg():
    return make_config("env.backend=analytic").env


def record(env_cfg, effects, episodes=4, steps=50, seed=0) -> Dataset:
    """Episodes of random force steps from random states on C MuJoCo with `effects`."""
    model = mujoco_spec(env_cfg, effects).compile()
    data = mujoco.MjData(model)
    frames = int(env_cfg.frames_per_step)
    dt = model.opt.timestep * frames
    ctrl_range = model.actuator_ctrlrange.copy()
    u = random_steps(seed, episodes, steps, dt, ctrl_range, min_hold=0.1, max_hold=0.3, scale=0.3)
    rng = np.random.default_rng(seed + 1)
    obs = np.zeros((episodes, steps + 1, model.nq + model.nv))
    for e in range(episodes):
        mujoco.mj_resetData(model, data)
        data.qpos[:] = rng.uniform(-0.5, 0.5, model.nq)
        obs[e, 0] = np.r_[data.qpos, data.qvel]
        for t in range(steps):
            data.ctrl[:] = u[e, t]
            mujoco.mj_step(model, data, frames)
            obs[e, t + 1] = np.r_[data.qpos, data.qvel]
    return Dataset(obs, u, dt)


def test_the_handoff_loads_in_mujoco_sysid_as_model_fields(sysid, env_cfg, tmp_path):
    effects = [
        named("coulomb_friction", "slider", force=18.0),
        named("viscous_damping", "hinge", coefficient=0.36),
        named("actuator_gain", "slide", gain=0.8),
        named("mass_scale", "pole", scale=1.5),
        named("actuator_deadzone", "slide", width=0.2),
        named("actuator_offset", "slide", offset=0.1),
    ]
    handoff = write_handoff(env_cfg, effects, tmp_path)
    assert handoff.params == tmp_path / "sysid" / "params.yaml"
    # MuJoCo's own reader, nothing of hds
    params = sysid.ParameterDict.load_from_disk(handoff.params)
    nominal = mujoco_spec(env_cfg).compile()
    pole_mass, hinge_damping = nominal.body("pole").mass[0], nominal.dof_damping[1]
    expected = {  # name: (value, lower bound): the effects on top of the model's own fields
        "joint/slider/frictionloss": (18.0, 0.0),
        "joint/hinge/damping[0]": (hinge_damping + 0.36, hinge_damping),
        "actuator/slide/gear[0]": (0.8 * nominal.actuator("slide").gear[0], None),
        "body/pole/mass": (1.5 * pole_mass, 0.05 * pole_mass),
    }
    assert sorted(params.keys()) == sorted(expected)
    for name, (value, lower) in expected.items():
        p = params[name]
        assert p.value[0] == pytest.approx(value) and p.nominal[0] == pytest.approx(value)
        assert np.isfinite(p.max_value[0]) and p.min_value[0] < value < p.max_value[0]
        if lower is not None:
            assert p.min_value[0] == pytest.approx(lower)
    # one line each for what MuJoCo has no field for, with the reason; also in the header
    assert [line.split(" ")[0] for line in handoff.not_handed_off] == [
        "actuator_deadzone@slide",
        "actuator_offset@slide",
    ]
    assert "limited control" in handoff.not_handed_off[1]
    header = handoff.params.read_text()
    assert all(f"#   {line}" in header for line in handoff.not_handed_off)
    # the MJCF it refers to holds the estimates; the modifiers write new values into it
    spec, loaded = load_handoff(handoff.params.parent)
    model = spec.compile()
    assert model.dof_frictionloss[0] == pytest.approx(18.0)
    assert model.dof_damping[1] == pytest.approx(hinge_damping + 0.36)
    inertia = model.body("pole").inertia.copy()
    new = {"joint/slider/frictionloss": 12.0, "joint/hinge/damping[0]": 0.2}
    new |= {"actuator/slide/gear[0]": 50.0, "body/pole/mass": 3.0 * pole_mass}
    loaded.update_from_vector(np.array([new[name] for name in loaded.keys()]))
    model = sysid.apply_param_modifiers(loaded, spec)
    assert model.dof_frictionloss[0] == pytest.approx(12.0)
    assert model.dof_damping[1] == pytest.approx(0.2)
    assert model.actuator("slide").gear[0] == pytest.approx(50.0)
    assert model.body("pole").mass[0] == pytest.approx(3.0 * pole_mass)
    np.testing.assert_allclose(model.body("pole").inertia, 2.0 * inertia, rtol=1e-6)


def test_an_offset_hands_off_as_the_actuators_affine_bias(sysid, tmp_path):
    env_cfg = make_config("env=emps", "real=none").env  # unlimited control: bias = offset
    handoff = write_handoff(env_cfg, [named("actuator_offset", "motor", offset=0.09)], tmp_path)
    assert handoff.handed_off == ["actuator/motor/biasprm[0]"] and not handoff.not_handed_off
    spec, _ = load_handoff(handoff.params.parent)
    model = spec.compile()
    data = mujoco.MjData(model)
    data.ctrl[0] = 1.5
    mujoco.mj_forward(model, data)
    gear = model.actuator("motor").gear[0]
    assert data.qfrc_actuator[0] == pytest.approx(gear * (1.5 + 0.09))  # force = gtau (u + o)


def test_a_sysid_fit_from_the_handoff_moves_to_the_truth(sysid, env_cfg, tmp_path):
    truth = [hidden("coulomb_friction", "slider", force=15.0)]
    truth += [hidden("viscous_damping", "hinge", coefficient=0.3)]
    data = record(env_cfg, truth)
    estimates = [
        named("coulomb_friction", "slider", force=18.0),
        named("viscous_damping", "hinge", coefficient=0.6),
    ]
    spec, params = load_handoff(write_handoff(env_cfg, estimates, tmp_path).params.parent)
    sequences = model_sequences(spec, data, horizon=10, stride=5)
    assert len(sequences.measured_rollout) == 4 * 9
    hinge_damping = mujoco_spec(env_cfg).compile().dof_damping[1]
    fields = {"joint/slider/frictionloss": 15.0, "joint/hinge/damping[0]": hinge_damping + 0.3}
    true = np.array([fields[name] for name in params.keys()])
    start = params.as_vector()
    assert np.all(np.abs(start - true) > 0.05 * true)
    residual_fn = sysid.build_residual_fn(models_sequences=[sequences])
    # the windows line up with MuJoCo's steps: at the truth the residual vanishes
    at_truth, _, _ = residual_fn(true, params)  # (sets params to `true`)
    assert np.abs(np.concatenate(at_truth)).max() < 1e-6
    params.update_from_vector(start)
    fitted, outcome = sysid.optimize(params, residual_fn, verbose=False, max_iters=20)
    np.testing.assert_allclose(fitted.as_vector(), true, rtol=0.01)
    # MuJoCo's own results: parameters, intervals and the identified MJCF
    sysid.save_results(tmp_path / "fit", [sequences], params, fitted, outcome, residual_fn)
    saved = sysid.ParameterDict.load_from_disk(tmp_path / "fit" / "params_x_hat.yaml")
    np.testing.assert_allclose(saved.as_vector(), fitted.as_vector())
    assert (tmp_path / "fit" / "confidence.pkl").is_file()


def test_load_handoff_names_a_parameter_the_model_lacks(env_cfg, tmp_path):
    handoff = write_handoff(env_cfg, [named("coulomb_friction", "slider", force=5.0)], tmp_path)
    text = handoff.params.read_text().replace("joint/slider/", "joint/rail/")
    handoff.params.write_text(text)
    with pytest.raises(ValueError, match="'joint/rail/frictionloss' names no joint"):
        load_handoff(handoff.params.parent)


@pytest.mark.skipif(not (EMPS / "DATA_EMPS.mat").is_file(), reason="no ../shared/data/emps")
def test_idim_ls_reproduces_the_published_emps_parameters():
    from hds.data import emps

    fitted = emps.idim_ls(EMPS / emps.ESTIMATION)
    for key in ("M", "Fv", "Fc", "offset"):
        assert fitted[key] == pytest.approx(emps.PUBLISHED[key], rel=0.01), key
    assert fitted["relative_error"] < 0.05  # the data README's "about 4%"
