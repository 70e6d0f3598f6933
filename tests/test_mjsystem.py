"""The own backends' System built from MuJoCo's model without brax (hds.envs.mjsystem): brax's
System to the last digit, and the programs traced on it brax's, op for op."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hds.envs import mjsystem
from hds.envs.system import ASSETS, brax_system, make_simulator


def own_model(xml):
    """The model an own backend's simulator is built on (effect motors added), or None."""
    sim, _ = make_simulator(xml, backend="generalized")
    model = sim.system.model
    return model if mjsystem.supported(model) else None


def brax_leaf(sys, path):
    for key in path:
        if isinstance(key, jax.tree_util.SequenceKey):
            sys = sys[key.idx]
        else:
            sys = getattr(sys, key.name)
    return sys


@pytest.mark.parametrize("xml", sorted(p.name for p in ASSETS.glob("*.xml")))
def test_every_field_is_brax_s_to_the_last_digit(xml):
    model = own_model(xml)
    if model is None:
        pytest.skip(f"{xml} is no tree of hinges and slides")
    own, brax = mjsystem.system_of(model), brax_system(model)
    for path, x in jax.tree_util.tree_leaves_with_path(own):
        y = brax_leaf(brax, path)
        where = jax.tree_util.keystr(path)
        assert type(x) is type(y) and x.dtype == y.dtype and x.weak_type == y.weak_type, where
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=where)
    assert own.link_names == brax.link_names and own.link_types == brax.link_types
    assert own.link_parents == brax.link_parents and own.num_links() == brax.num_links()
    assert (own.q_size(), own.qd_size(), own.act_size()) == (
        brax.q_size(),
        brax.qd_size(),
        brax.act_size(),
    )


def test_a_model_outside_the_own_backends_reach_gets_brax_s_system_and_its_refusal(tmp_path):
    xml = tmp_path / "ball.xml"
    xml.write_text(
        "<mujoco><worldbody><body name='b'><joint name='j' type='ball'/>"
        "<geom type='sphere' size='0.1' mass='1' contype='0' conaffinity='0'/></body>"
        "</worldbody></mujoco>"
    )
    sim, _ = make_simulator(str(xml), backend="generalized")
    assert not mjsystem.supported(sim.system.model)
    with pytest.raises(ValueError, match="use backend=generalized"):
        make_simulator(str(xml), backend="tree")


@pytest.mark.parametrize("backend", ["analytic", "tree"])
def test_a_step_traced_on_it_is_the_program_traced_on_brax_s(backend):
    """Effects that edit the System (mass, gain, friction) included: the same program, so the
    same numbers, as the backends had on brax's System."""
    effects = [
        {"name": "mass_scale", "target": "pole", "params": {}},
        {"name": "actuator_gain", "target": "slide", "params": {}},
        {"name": "viscous_damping", "target": "slider", "params": {}},
    ]
    sim, params = make_simulator("cartpole.xml", backend=backend, frames=2, effects=effects)
    assert isinstance(sim.sys, mjsystem.System)
    on_brax = sim.with_sys(brax_system(sim.system.model))

    def program(s):
        def step(params, q, qd, u):
            return s.step(params, s.init(q, qd, params), u).pipeline.q

        zeros = jnp.zeros(2)
        return jax.jit(step).lower(params, zeros, zeros, jnp.zeros(1)).as_text()

    assert program(sim) == program(on_brax)
