"""The continuation (hds/algo/continuation.py) on its own: one state structure for every
setting, and a ramp that waits for a solved task, pauses after a failed epoch and keeps the
best policy once it has ended."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hds.algo.continuation import Continuation

POLICY = {"w": jnp.zeros(3)}


def test_the_continuation_s_state_has_one_structure_for_every_setting():
    settings = [
        Continuation(10),
        Continuation(10, ramp=(2, 6), solved_at=0.0, solved_for=3, pauses=True, keep_best=True),
        Continuation(10, horizon=30, horizon_start=5, horizon_full_at=5.0),
    ]
    structures = set()
    for continuation in settings:
        progress = continuation.init(POLICY)
        point = continuation.at(progress, 0)
        later = continuation.update(progress, 0, point, POLICY, jnp.float32(1.0))
        structures |= {jax.tree.structure(progress), jax.tree.structure(later)}
    assert len(structures) == 1


def test_the_ramp_waits_pauses_and_keeps_the_best_policy_once_ended():
    """A ramp over epochs 2-6 of 10 that waits for 2 solved epochs in a row: solved at epochs
    1-2, it starts one epoch late (3), stands still after the failed epoch 4, ends at 7; the
    policy kept is epoch 7's, the first with the best return at the ramp's end."""
    continuation = Continuation(
        10, ramp=(2, 6), solved_at=0.0, solved_for=2, pauses=True, keep_best=True
    )
    returns = [-1, 1, 1, 1, -1, 1, 1, 1, 1, 1]
    progress, shares = continuation.init(POLICY), []
    for epoch, ret in enumerate(returns):
        point = continuation.at(progress, epoch)
        shares.append(float(point.share))
        policy = {"w": jnp.full(3, float(epoch))}
        progress = continuation.update(progress, epoch, point, policy, jnp.float32(ret))
    np.testing.assert_allclose(shares, [0, 0, 0, 0.25, 0.5, 0.5, 0.75, 1, 1, 1])
    assert int(progress.solved) == 2 and int(progress.paused) == 1
    kept = continuation.final_policy(progress, {"w": jnp.full(3, 9.0)})
    np.testing.assert_array_equal(kept["w"], [7.0, 7.0, 7.0])


@pytest.mark.parametrize("start, counted", [(0, None), (5, 5), (30, None)])
def test_the_horizon_curriculum_counts_the_first_steps_at_the_first_epoch(start, counted):
    continuation = Continuation(10, horizon=30, horizon_start=start, horizon_full_at=5.0)
    weights = continuation.at(continuation.init(POLICY), 0).counted
    if counted is None:
        assert weights is None
    else:
        assert float(weights.sum()) == counted and float(weights[:counted].min()) == 1.0
        assert float(continuation.at(continuation.init(POLICY), 5).counted.sum()) == 30


def test_a_state_flattens_as_the_flax_struct_it_was_so_checkpoints_keep_their_structure():
    """hds's states (this continuation's, the trainer's, the simulators') are
    hds.utils.pytree dataclasses, no longer flax structs: the same leaves under the same key
    paths (what a checkpoint stores), the same `replace`, frozen all the same."""
    import dataclasses

    from flax import struct

    from hds.utils.pytree import pytree_dataclass

    @pytree_dataclass
    class Ours:
        a: object
        b: object

    @struct.dataclass
    class Flax:
        a: object
        b: object

    def paths(tree):
        leaves = jax.tree_util.tree_leaves_with_path(tree)
        return [(jax.tree_util.keystr(p), np.asarray(x).tolist()) for p, x in leaves]

    ours, theirs = (cls(np.arange(2.0), {"c": np.zeros(1)}) for cls in (Ours, Flax))
    assert paths(ours) == paths(theirs) == [(".a", [0.0, 1.0]), (".b['c']", [0.0])]
    assert paths(ours.replace(a=np.ones(1))) == paths(theirs.replace(a=np.ones(1)))
    doubled = jax.tree.map(lambda x: 2 * x, ours)
    assert isinstance(doubled, Ours) and doubled.a.tolist() == [0.0, 2.0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        ours.a = None
