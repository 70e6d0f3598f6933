"""An effect is one object: adding one is a class and `register(...)`, nothing else.

The toy effect here, a constant force on a joint, is defined and registered in this file only;
configs accept it, the analytic simulator steps and trains with it, the C MuJoCo plant applies
it. Its physics is checked against a built-in effect that exerts the same force: an actuator
offset of F / gear on the cart's actuator (u = 0 stays inside the control range).

Cost: analytic backend only (compiles in seconds); one tiny training.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import make_config

from hds.algo.pods import make_train_from_config
from hds.effects import LIBRARY, Effect, Param, place, register
from hds.effects.base import JOINT, SUBSTEP
from hds.envs import make_env
from hds.envs.system import load_spec
from hds.gap import Evaluator
from hds.real import make_plant
from hds.real.mujoco_plant import MujocoPlant
from tests.test_train import TINY  # the analytic backend, a tiny budget


class ForceBias(Effect):
    name = "force_bias"
    target_kind = JOINT
    description = "a constant force on the joint"
    physical_name = "constant force bias"
    params = (Param("force", "N or N m", 0.0),)
    stage = SUBSTEP

    def substep(self, site, p, state, u, force, q, qd, h, sharpness, gradient_sharpness):
        return u, force.at[site.index].add(p["force"]), state

    def plant_force(self, site, p):
        return p["force"]


FORCE = 20.0  # N on the cart
TOY = f"{{name: force_bias, target: slider, params: {{force: {FORCE}}}}}"
T = 15  # environment steps of 0.04 s


@pytest.fixture(scope="module", autouse=True)
def toy_effect():
    register(ForceBias())
    yield
    del LIBRARY["force_bias"]  # other test modules of this process see the library as it was


@pytest.fixture(scope="module")
def cfg():
    return make_config("env.backend=analytic", f"env.effects=[{TOY}]")


def same_force(env_cfg) -> dict:
    """The built-in effect that exerts FORCE on the cart: an offset of FORCE / gear."""
    gear = float(load_spec(env_cfg.xml).compile().actuator("slide").gear[0])
    return {"name": "actuator_offset", "target": "slide", "params": {"offset": FORCE / gear}}


def hanging_start(episodes: int = 3):
    q0 = np.tile([0.0, np.pi], (episodes, 1)) + np.linspace(-0.1, 0.1, episodes)[:, None]
    return q0, np.zeros_like(q0)


def sim_trajectory(env) -> np.ndarray:
    """[episodes, T, n_obs] with zero control from `hanging_start`."""
    q0, qd0 = hanging_start()
    u = jnp.zeros((T, env.sim.n_act))

    def one(q, qd):
        def step(state, ut):
            state = env.sim.step(env.params, state, ut)
            return state, env.sim.observe(env.params, state)

        return jax.lax.scan(step, env.sim.init(q, qd, env.params), u)[1]

    return np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(q0), jnp.asarray(qd0)))


def plant_trajectory(plant) -> np.ndarray:
    q0, qd0 = hanging_start()
    plant.reset(q0, qd0)
    return np.stack([plant.step(np.zeros((len(q0), 1))) for _ in range(T)], axis=1)


def test_a_registered_effect_is_in_the_config_schema_and_validated(cfg):
    assert [e.name for e in cfg.env.effects] == ["force_bias"]
    with pytest.raises(ValueError, match="force_bias.*no parameter"):
        make_config(
            "env.backend=analytic",
            "env.effects=[{name: force_bias, target: slider, params: {gain: 1.0}}]",
        )
    with pytest.raises(ValueError, match="acts on a joint"):
        make_config("env.backend=analytic", "env.effects=[{name: force_bias, target: slide}]")


@pytest.fixture(scope="module")
def nominal(cfg) -> np.ndarray:
    """The trajectory of the simulator with no effect."""
    return sim_trajectory(make_env(cfg.env, effects=[]))


def test_the_simulator_applies_it_as_the_same_force_from_an_actuator(cfg, nominal):
    toy = sim_trajectory(make_env(cfg.env))
    offset = sim_trajectory(make_env(cfg.env, effects=[same_force(cfg.env)]))
    np.testing.assert_allclose(toy, offset, atol=1e-5)
    assert np.all(toy[:, -1, 0] - nominal[:, -1, 0] > 0.01)  # it pushed the cart forward


def test_the_mujoco_plant_applies_it_and_agrees_with_the_simulator(cfg):
    toy = plant_trajectory(MujocoPlant(cfg.env, cfg.env.effects))
    offset = plant_trajectory(MujocoPlant(cfg.env, [same_force(cfg.env)]))
    np.testing.assert_allclose(toy, offset, atol=1e-9)
    np.testing.assert_allclose(toy, sim_trajectory(make_env(cfg.env)), atol=2e-3)
    assert np.all(toy[:, -1, 0] - plant_trajectory(MujocoPlant(cfg.env))[:, -1, 0] > 0.01)


@pytest.mark.slow  # make test-slow: keeps make test under 10 min cold
def test_pods_trains_with_it_and_the_policy_holds_on_the_plant():
    """Trained on the analytic simulator carrying the toy effect, evaluated on the C MuJoCo
    plant carrying it too (and nothing else): the policy improves on both."""
    cfg = make_config(*TINY, f"env.effects=[{TOY}]", "real=mujoco", f"real.effects=[{TOY}]")
    env = make_env(cfg.env)
    trainer = make_train_from_config(cfg, env)
    keys = jax.vmap(jax.random.PRNGKey)(jnp.arange(2))
    state, _ = jax.jit(jax.vmap(trainer.train, in_axes=(0, None)))(keys, trainer.default_hparams)
    before = jax.vmap(trainer.init, in_axes=(0, None))(keys, trainer.default_hparams).policy
    evaluator = Evaluator(env, trainer.policy, make_plant(cfg.real, cfg.env), episodes=8)
    for returns in (evaluator.sim_returns, evaluator.real_returns):
        r0, r1 = returns(before).mean(axis=1), returns(state.policy).mean(axis=1)
        assert np.all(r1 > r0 + 0.1 * np.abs(r0)), (returns.__name__, r0, r1)


def test_registration_refuses_twice_and_incomplete_and_the_plant_names_a_missing_law(cfg):
    with pytest.raises(ValueError, match="'force_bias' is registered already"):
        register(ForceBias())

    class Incomplete(Effect):
        name = "incomplete"

    with pytest.raises(ValueError, match=r"Incomplete lacks \['target_kind'"):
        register(Incomplete())

    class Unplanted(ForceBias):
        name = "unplanted_force"
        plant_force = Effect.plant_force

    register(Unplanted())
    try:
        effects = [{"name": "unplanted_force", "target": "slider", "params": {"force": 1.0}}]
        with pytest.raises(NotImplementedError, match="'unplanted_force'.*no plant_force"):
            MujocoPlant(cfg.env, effects)
    finally:
        del LIBRARY["unplanted_force"]


# The generic joint force terms (hds.effects.force_terms): gap discovery's terms beyond the library


@pytest.mark.parametrize("backend", ["analytic", "tree"])
def test_force_terms_with_a_known_stiffness_are_the_mjcf_joint_stiffness(
    cfg, nominal, tmp_path, backend
):
    """A term -k q on the rail steps as the same MJCF with joint stiffness k does, on the
    analytic and the tree backends (the effect acts through the backends' shared path)."""
    spec = load_spec(cfg.env.xml)
    assert spec.joint("slider").stiffness[0] == 0.0
    spec.joint("slider").stiffness[0] = 30.0
    path = tmp_path / "cartpole_spring.xml"
    path.write_text(spec.to_xml())
    spring = {"name": "joint_force_terms", "target": "slider", "params": {"q": -30.0}}
    env_cfg = dataclasses.replace(cfg.env, backend=backend)
    terms = sim_trajectory(make_env(env_cfg, effects=[spring]))
    stiff = sim_trajectory(make_env(dataclasses.replace(env_cfg, xml=str(path)), effects=[]))
    np.testing.assert_allclose(terms, stiff, atol=1e-5)
    assert np.abs(terms - nominal)[:, -1, 0].max() > 0.01  # the spring pulled the carts


def test_force_terms_sum_coefficient_times_feature_and_differentiate_in_the_coefficients(cfg):
    """The joint force, by hand: every feature of the vocabulary at once on the hinge, the
    control's term from the first actuator; d force / d coefficient is the feature."""
    coefficients = {"q": 1.0, "sin_q": 2.0, "cos_q": -3.0, "qd": 0.5}
    coefficients |= {"sign_qd": -0.7, "abs_qd_qd": -0.2, "u": 0.3}
    env = make_env(cfg.env, effects=[])
    names = env.sim.targets
    placed, params = place(
        [{"name": "joint_force_terms", "target": "hinge", "params": coefficients}], names
    )
    hinge = names["joint"]["hinge"]
    q, qd, u = jnp.array([0.3, 1.2]), jnp.array([-0.4, -2.0]), jnp.array([0.8])
    force = placed.substep(params, {}, u, q, qd, 0.01, None)[1]
    expected = (
        1.0 * 1.2
        + 2.0 * np.sin(1.2)
        - 3.0 * np.cos(1.2)
        + 0.5 * -2.0
        - 0.7 * -1.0
        - 0.2 * 2.0 * -2.0
        + 0.3 * 0.8
    )
    assert float(force[hinge]) == pytest.approx(expected, rel=1e-5)
    assert float(force[names["joint"]["slider"]]) == 0.0

    def hinge_force(p):
        return placed.substep((p,), {}, u, q, qd, 0.01, 50.0)[1][hinge]

    grad = jax.grad(hinge_force)(params[0])
    assert float(grad["abs_qd_qd"]) == pytest.approx(-4.0)
    assert float(grad["sin_q"]) == pytest.approx(np.sin(1.2), rel=1e-5)
    assert float(grad["sign_qd"]) == pytest.approx(np.tanh(50.0 * -2.0))  # smoothed sign


@pytest.mark.parametrize(
    "effect, message",
    [
        ("{name: joint_force_terms, target: slider, params: {q2: 1.0}}", "no parameter \\['q2'\\]"),
        ("{name: joint_force_terms, target: rail, params: {q: 1.0}}", "no joint 'rail'"),
        (
            "{name: joint_force_terms, target: slider, params: {u: 1.0, actuator: 3}}",
            "actuator = 3",
        ),
    ],
)
def test_force_terms_naming_an_unknown_feature_joint_or_actuator_are_refused(effect, message):
    with pytest.raises(ValueError, match=message) as err:
        make_config("env.backend=analytic", f"env.effects=[{effect}]")
    assert "\n" not in str(err.value)


def test_the_mujoco_plant_refuses_force_terms_with_one_line(cfg):
    spring = {"name": "joint_force_terms", "target": "slider", "params": {"q": -30.0}}
    with pytest.raises(ValueError, match="joint_force_terms@slider.*MJCF.*real=brax"):
        MujocoPlant(cfg.env, [spring])
