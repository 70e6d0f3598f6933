"""Domain randomization (`method=dr`): draws lie within their ranges, a config without ranges is
refused before anything compiles, and a range of no width trains exactly as that value alone."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from hds import simulators
from hds.algo.pods import make_train_from_config
from hds.algo.randomize import effect_ranges, randomized_env, sample_effects
from hds.envs import make_env
from tests.conftest import make_config
from tests.test_train import TINY

FRICTION = "{name: coulomb_friction, target: slider, %s}"


def ranged(low: float, high: float) -> str:
    gain = "{name: actuator_gain, target: slide, ranges: {gain: [0.8, 1.2]}}"
    return f"dr.effects=[{FRICTION % f'ranges: {{force: [{low}, {high}]}}'}, {gain}]"


def test_draws_lie_within_their_ranges_and_cover_them():
    cfg = make_config("method=dr", ranged(5.0, 40.0))
    low, high = effect_ranges(cfg, randomized_env(cfg))
    draws = sample_effects(jax.random.PRNGKey(0), low, high, 2000)
    for name, param, lo, hi in (
        ("friction", "force", 5.0, 40.0),
        ("gain", "gain", 0.8, 1.2),
    ):
        values = np.asarray(draws[0 if name == "friction" else 1][param])
        assert values.shape == (2000,)
        assert values.min() >= lo and values.max() <= hi
        # uniform: both ends of the range are reached within 1% of its width
        assert values.min() < lo + 0.01 * (hi - lo) and values.max() > hi - 0.01 * (hi - lo)


@pytest.mark.parametrize(
    "overrides, message",
    [
        (("method=dr",), "dr.effects, which is empty"),
        (("method=dr", ranged(40.0, 5.0)), "must be [low, high]"),
        (
            (
                "method=dr",
                "dr.effects=[{name: coulomb_friction, target: cart_wheel, "
                "ranges: {force: [0, 1]}}]",
            ),
            "no joint 'cart_wheel'",
        ),
    ],
)
def test_dr_without_valid_ranges_is_refused(overrides, message):
    with pytest.raises(ValueError) as err:
        make_config(*overrides)
    assert message in str(err.value)


def _trained(cfg, env, randomization=None):
    """A trainer's compiled `train` for one seed: hparams -> (policy, training returns)."""
    trainer = make_train_from_config(cfg, env, randomization=randomization)
    train = jax.jit(lambda h: trainer.train(jax.random.PRNGKey(3), h))

    def run(hparams_of=lambda h: h):
        state, metrics = train(hparams_of(trainer.default_hparams))
        return state.policy, np.asarray(metrics["return"])

    return run


@pytest.mark.slow
def test_a_range_of_no_width_trains_as_that_value_alone():
    plain = make_config(
        *TINY,
        "method=pods_cl_effects",
        "anneal.ramp_pauses=true",  # as method=dr's ramp
        f"env.effects=[{FRICTION % 'params: {force: 20.0}'}]",
    )
    plain_policy, plain_return = _trained(plain, make_env(plain.env))()
    cfg = make_config(*TINY, "method=dr", f"dr.effects=[{FRICTION % 'ranges: {force: [20, 20]}'}]")
    simulator = simulators.of(cfg).restore(cfg, None)  # the env and its randomization
    run = _trained(cfg, simulator.env, simulator.randomization)
    policy, returns = run()
    for a, b in zip(jax.tree.leaves(plain_policy), jax.tree.leaves(policy)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(plain_return, returns, rtol=1e-5)

    def wide(hparams):  # the same program, the friction drawn from [0, 80] N
        low, high = hparams["effect_ranges"]
        shift = lambda tree, by: jax.tree.map(lambda x: x + by, tree)  # noqa: E731
        return {**hparams, "effect_ranges": (shift(low, -20.0), shift(high, 60.0))}

    assert np.abs(run(wide)[1] - returns).max() > 1e-3
