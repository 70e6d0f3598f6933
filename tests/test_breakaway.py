"""Dry friction with a Stribeck (breakaway) peak, `breakaway_friction` (hds.effects.friction):
its law's limits (no peak is Coulomb friction; far above the Stribeck velocity it is the
sliding level), finite gradients at rest, the C MuJoCo plant's law against the simulator's on
a rollout, and gap discovery, which tries it only as a refinement of a named Coulomb friction:
on a rail with a static peak it names both levels, on one without it keeps Coulomb's law.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import make_config

from hds.effects.apply import Site
from hds.effects.base import PlantLoads
from hds.effects.library import candidate_effects, default_candidates, effect_type
from hds.envs import make_env
from hds.real.brax_plant import BraxPlant
from hds.real.mujoco_plant import MujocoPlant

BREAKAWAY, COULOMB = effect_type("breakaway_friction"), effect_type("coulomb_friction")
H, MOBILITY = 0.01, 1 / 15.5  # a substep and the cart's inverse inertia (kg^-1)
SITE = Site("breakaway_friction", "slider", 0, mobility=MOBILITY)
T = 15  # environment steps of the rollouts: 0.6 s


def effect(name, target, **params):
    return {"name": name, "target": target, "params": params}


def force(effect_, params, v, sharpness=50.0, gradient_sharpness=None):
    """The joint force of one effect on a one-dof joint moving at speed v."""
    qd = jnp.atleast_1d(jnp.asarray(v, jnp.float32))
    p = {k: jnp.float32(x) for k, x in params.items()}
    _, f, _ = effect_.substep(
        SITE, p, None, jnp.zeros(1), jnp.zeros(1), qd * 0, qd, H, sharpness, gradient_sharpness
    )
    return f[0]


def test_it_is_an_opt_in_candidate_and_the_lab_replica_is_none():
    assert "breakaway_friction" in candidate_effects()
    assert "breakaway_friction" not in default_candidates()
    assert "stribeck_friction" not in candidate_effects()
    assert BREAKAWAY.refines == ("coulomb_friction", "peak")


@pytest.mark.parametrize("sharpness", [None, 50.0, 1e4])
def test_without_a_peak_it_is_coulomb_friction(sharpness):
    """peak = 0 is Coulomb's law exactly, smoothing and its cap included (the cap binds at
    k = 1e4: 2 / (h F w) = 258 for 12 N on the cart)."""
    for v in [-1.0, -0.03, -1e-4, 0.0, 1e-4, 0.02, 0.5]:
        a = force(BREAKAWAY, {"force": 12.0, "peak": 0.0, "velocity": 0.05}, v, sharpness)
        b = force(COULOMB, {"force": 12.0}, v, sharpness)
        assert float(a) == pytest.approx(float(b), abs=1e-6)


def test_it_falls_from_the_breakaway_level_at_rest_to_the_sliding_level_far_above_vs():
    params = {"force": 12.0, "peak": 6.0, "velocity": 0.05}
    # the plant's law: MuJoCo's frictionloss, the magnitude at the step's starting speed
    loads = PlantLoads(np.zeros((3, 1)), np.zeros((3, 1)), np.zeros((3, 1)))
    qd = np.array([[0.0], [0.05], [1.0]])
    BREAKAWAY.plant_substep(SITE, params, None, loads, qd * 0, qd, H)
    np.testing.assert_allclose(loads.frictionloss[:, 0], [18.0, 12.0 + 6.0 / np.e, 12.0])
    # the simulator's: against the motion, the sliding level 20 Stribeck velocities up
    assert float(force(BREAKAWAY, params, 1.0)) == pytest.approx(-12.0, rel=1e-5)
    assert float(force(BREAKAWAY, params, -1.0)) == pytest.approx(12.0, rel=1e-5)
    # between the two levels at the Stribeck velocity (the tanh saturated: |k v| = 2.5)
    mid = -float(force(BREAKAWAY, params, 0.05))
    assert 12.0 < mid < 12.0 + 6.0 / np.e + 1e-4


@pytest.mark.parametrize("gradient_sharpness", [None, 5.0])
def test_its_gradients_are_finite_at_rest(gradient_sharpness):
    def f(v, force_, peak, velocity):
        params = {"force": force_, "peak": peak, "velocity": velocity}
        return force(BREAKAWAY, params, v, 50.0, gradient_sharpness)

    grads = jax.grad(f, argnums=(0, 1, 2, 3))(0.0, 12.0, 6.0, 0.05)
    assert all(np.isfinite(float(g)) for g in grads)
    assert float(grads[0]) < 0  # it opposes a small motion from rest
    # and at a fit's start: no peak, where the Stribeck velocity means nothing yet
    grads = jax.grad(f, argnums=(0, 1, 2, 3))(0.0, 12.0, 0.0, 0.1)
    assert all(np.isfinite(float(g)) for g in grads)


@pytest.fixture(scope="module")
def cartpole():
    return make_config("real=none", "env.backend=analytic").env


def rollout(plant, q0, qd0, u):
    obs, states = [plant.reset(q0, qd0)], [np.concatenate(plant.state(), 1)]
    for t in range(u.shape[1]):
        obs.append(plant.step(u[:, t]))
        states.append(np.concatenate(plant.state(), 1))
    return np.stack(states, 1)


def test_the_plants_law_and_the_simulators_agree_on_a_rollout(cartpole):
    """A push between the sliding (10 N) and the breakaway (16 N) level holds the plant's cart
    where Coulomb friction at the sliding level lets it go, and the simulator holds it too
    (short of the plant by its tanh law's creep); coasting to rest, the simulator follows
    the plant closer than Coulomb friction at the sliding level does."""
    peaked = [effect("breakaway_friction", "slider", force=10.0, peak=6.0, velocity=0.05)]
    coulomb = [effect("coulomb_friction", "slider", force=10.0)]
    q0 = np.tile([0.0, np.pi], (2, 1))  # the pole hanging
    qd0 = np.array([[0.15, 0.0], [0.0, 0.0]])
    u = np.zeros((2, T, 1))
    u[1] = 0.13  # 13 N
    plant = rollout(MujocoPlant(cartpole, peaked), q0, qd0, u)
    sim = rollout(BraxPlant(make_env(cartpole, effects=peaked)), q0, qd0, u)
    sliding = rollout(MujocoPlant(cartpole, coulomb), q0, qd0, u)
    pushed, coasting, speed = 1, 0, 2
    assert abs(plant[pushed, -1, 0]) < 0.005  # MuJoCo's soft frictionloss creeps a little
    assert sliding[pushed, -1, 0] > 0.03
    assert sim[pushed, -1, 0] < 0.5 * sliding[pushed, -1, 0]
    to_sim = np.abs(plant[coasting] - sim[coasting]).max(0)
    to_coulomb = np.abs(plant[coasting] - sliding[coasting]).max(0)
    assert to_coulomb[speed] > 5e-3 and to_sim[speed] < 0.5 * to_coulomb[speed]


# Discovery: a refinement of a named Coulomb friction ------------------------------------------


def _discover(cartpole, hidden):
    import test_discover as td

    from hds.discover import DiscoverConfig, discover

    task = make_env(cartpole).task
    cfg = DiscoverConfig(stride=2, effects=[*default_candidates(), "breakaway_friction"])
    return discover(td.record(MujocoPlant(cartpole, hidden), task), cartpole, cfg)


@pytest.mark.slow  # two discoveries with their own engine: about 50 s each on 2 cores
def test_discovery_names_both_levels_of_a_rail_with_a_static_peak_and_keeps_coulomb_without(
    cartpole,
):
    """A rail with 12 N sliding and 18 N breakaway friction: Coulomb friction is named first,
    the peak refines it (Coulomb's fit replaced), both levels within 25% of the truth, nothing
    else named. A rail with Coulomb friction alone (MuJoCo's soft frictionloss, 15 N): its
    law stays Coulomb's, no peak named."""
    peaked = effect("breakaway_friction", "slider", force=12.0, peak=6.0, velocity=0.05)
    result = _discover(cartpole, [peaked])
    assert [(e.name, e.target) for e in result.missing_effects] == [
        ("breakaway_friction", "slider")
    ]
    (found,) = result.missing_effects
    assert found.params["force"] == pytest.approx(12.0, rel=0.25)
    assert found.params["force"] + found.params["peak"] == pytest.approx(18.0, rel=0.25)
    assert "coulomb_friction@slider" in result.to_json()["dropped_proxies"]

    result = _discover(cartpole, [effect("coulomb_friction", "slider", force=15.0)])
    assert [(e.name, e.target) for e in result.missing_effects] == [("coulomb_friction", "slider")]
    assert result.missing_effects[0].params["force"] == pytest.approx(15.0, rel=0.1)
