"""Orbax checkpoints of a training run: the train state (policy, optimizer, epoch, RNG key) and
the metric history so far, so a run started again on the same directory resumes exactly."""

from __future__ import annotations

from pathlib import Path

import jax
import orbax.checkpoint as ocp


class Checkpoints:
    def __init__(self, directory: str | Path, keep: int = 3):
        self.directory = Path(directory).absolute()
        self.manager = ocp.CheckpointManager(
            self.directory, options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True)
        )

    def latest(self) -> int | None:
        return self.manager.latest_step()

    def save(self, epoch: int, state, meta: dict) -> None:
        self.manager.save(
            epoch,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta)
            ),
        )
        self.manager.wait_until_finished()

    def restore(self, like, epoch: int | None = None):
        """(state, meta) of `epoch` (default: the latest); `like` gives the state's structure."""
        epoch = self.latest() if epoch is None else epoch
        if epoch is None:
            raise FileNotFoundError(
                f"no checkpoint in {self.directory}: train first, or point to a run directory "
                "that has a checkpoints/ folder"
            )
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like)
        restored = self.manager.restore(
            epoch,
            args=ocp.args.Composite(
                state=ocp.args.StandardRestore(abstract), meta=ocp.args.JsonRestore()
            ),
        )
        return restored.state, restored.meta

    def close(self) -> None:
        self.manager.close()
