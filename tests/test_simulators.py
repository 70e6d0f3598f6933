"""The registry of simulator kinds (hds.simulators): every name a config accepts has its kind,
each kind labels the rows and builds what its method trains on, and a new kind is one class
plus one registration."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from hds import simulators
from hds.config import kinds
from hds.envs import make_env
from tests.conftest import make_config

FRICTION = "{name: coulomb_friction, target: slider, ranges: {force: [5, 40]}}"


def test_every_simulator_a_config_accepts_is_a_registered_kind():
    """The names are declared once (hds.config.kinds): each builds its class, which carries
    the declared name and light facts."""
    assert set(kinds.KINDS) >= {"nominal", "corrected", "real", "randomized"}
    for name, declared in kinds.KINDS.items():
        kind = simulators.load(name)
        assert isinstance(kind, simulators.SimulatorKind)
        assert (kind.name, kind.discovers) == (name, declared.discovers)
    assert [k.name for k in kinds.KINDS.values() if k.discovers] == ["corrected"]
    with pytest.raises(ValueError, match="simulator = 'exact' is not a registered kind"):
        simulators.load("exact")


def test_each_kind_restores_what_its_method_trains_on():
    """nominal: the env as configured; real: the plant's effects at each run's friction gap
    (stacked per run); randomized: dr.effects at their ranges' middle, and the randomization
    handed to the trainer draws within the ranges."""
    cfg = make_config("real=brax", "sweep.friction_gap=[0.5,2]")
    nominal = simulators.of(cfg).restore(cfg, None)
    assert nominal.effects is None and nominal.randomization is None
    assert not nominal.env.sim.effects.sites
    oracle = simulators.of(cfg, "oracle").restore(cfg, None)
    (force,) = jax.tree.leaves(oracle.effects)
    np.testing.assert_allclose(np.asarray(force), [10.0, 40.0])  # 20 N at gaps 0.5 and 2
    dr = make_config("method=dr", f"dr.effects=[{FRICTION}]")
    built = simulators.of(dr).build(dr, make_env(dr.env), None, None)
    assert [(e.name, e.target) for e in built.env.sim.effects.sites] == [
        ("coulomb_friction", "slider")
    ]
    (middle,) = jax.tree.leaves(built.env.params)
    assert float(np.asarray(middle)) == pytest.approx(22.5)
    hparams = built.randomization.hparams()
    (draws,) = jax.tree.leaves(built.randomization.draw(jax.random.PRNGKey(0), hparams, 500))
    assert draws.shape == (500,) and 5.0 <= draws.min() and draws.max() <= 40.0


def test_a_new_kind_is_one_class_and_one_registration():
    @simulators.register
    class Doubled(simulators.SimulatorKind):
        """A made-up kind: the env with twice its configured friction."""

        name = "doubled_test_kind"
        about = "the env with twice its friction"
        tags = ("x2",)

        def restore(self, cfg, run_dir):
            return simulators.Simulator(make_env(cfg.env, friction_gap=2.0))

    try:
        kind = simulators.load("doubled_test_kind")
        cfg = make_config("method=hds")
        assert kind.label(cfg) == "hds+mlp+x2"
        assert kind.build(cfg, None, None, None).env.sim.dt > 0
        description, env_cfg, _ = kind.trained_on(cfg, cfg.runs()[0], None)
        assert description["simulator"] == "doubled_test_kind" and env_cfg is cfg.env
        with pytest.raises(ValueError, match="registered twice"):
            simulators.register(Doubled)
        # declared by its registration: a config names it with no other change
        assert make_config("simulator=doubled_test_kind").simulator == "doubled_test_kind"
    finally:
        del simulators.KINDS["doubled_test_kind"], kinds.KINDS["doubled_test_kind"]
