"""Orbax checkpoints of a training run: the train state (policy, optimizer, epoch, RNG key) and
the metric history so far, so a run started again on the same directory resumes exactly.

A checkpoint that cannot be read (a file truncated by a full disk or a crash outside Orbax's
atomic write) is skipped with a warning naming it and why, and the one before it restored;
training, which writes that epoch again, deletes it (a reader, such as `load_policy`, does
not).
A checkpoint whose arrays do not fit the state (another network, batch or optimizer) is not
damaged: restoring it is refused, naming the arrays that differ. One written by hds before the
train state had one structure for every configuration stored only the `progress` arrays its
configuration used: the others (which that configuration does not read) restore at the
state's own values (zeros where the state is abstract)."""

from __future__ import annotations

import contextlib
import errno
import logging
from pathlib import Path

import jax
import numpy as np

log = logging.getLogger("hds")


def _orbax():
    """orbax.checkpoint, imported where a checkpoint is written or read: a process that imports
    this module (hds.experiment does) but never checkpoints skips Orbax's ~0.3 s import."""
    import orbax.checkpoint as ocp

    return ocp


# arrays under these names (TrainState.progress) an older checkpoint may lack
OPTIONAL = ("progress.",)


class Checkpoints:
    def __init__(self, directory: str | Path, keep: int = 3):
        ocp = _orbax()
        self.directory = Path(directory).absolute()
        self.manager = ocp.CheckpointManager(
            self.directory,
            # synchronous: training waits for every save anyway (a checkpoint is complete
            # before the next epoch runs), and an async manager then reports that wait at the
            # next save as a warning to checkpoint less often
            options=ocp.CheckpointManagerOptions(
                max_to_keep=keep, create=True, enable_async_checkpointing=False
            ),
            # known before the first restore: item_metadata reads the state's arrays with it
            item_handlers={
                "state": ocp.StandardCheckpointHandler(),
                "meta": ocp.JsonCheckpointHandler(),
            },
        )

    def latest(self) -> int | None:
        return self.manager.latest_step()

    def save(self, epoch: int, state, meta: dict) -> None:
        """Write `epoch`'s checkpoint. A full disk raises OSError(ENOSPC) naming the directory
        (one line at the command: free space and start again, it resumes), without the
        tracebacks Orbax's threads log for it (hundreds of lines); any other failure of the
        save re-emits what Orbax logged, then raises."""
        ocp = _orbax()
        with _held_back(logging.getLogger("absl")) as held:  # Orbax logs through absl
            try:
                self.manager.save(
                    epoch,
                    args=ocp.args.Composite(
                        state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta)
                    ),
                )
                self.manager.wait_until_finished()
            except Exception as err:
                if _disk_full(err):
                    # let Orbax's threads end before the program does: else each of them
                    # prints "Event loop is closed" at exit
                    with contextlib.suppress(Exception):
                        self.manager.close()
                    raise OSError(
                        errno.ENOSPC,
                        f"No space left on device for checkpoint {epoch}",
                        str(self.directory),
                    ) from None
                failed = err
            else:
                failed = None
        for record in held:
            logging.getLogger(record.name).handle(record)
        if failed is not None:
            raise failed

    def restore(self, like, epoch: int | None = None, resuming: bool = False):
        """(state, meta) of `epoch` (default: the latest readable one); `like` gives the
        state's structure. `resuming` (training): an unreadable checkpoint is deleted, as
        training writes that epoch again; otherwise (reading a policy) it is left in place."""
        ocp = _orbax()
        epochs = sorted(self.manager.all_steps(), reverse=True) if epoch is None else [epoch]
        if not epochs:
            raise FileNotFoundError(
                f"no checkpoint in {self.directory}: train first, or point to a run directory "
                "that has a checkpoints/ folder"
            )
        abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like)
        for i, step in enumerate(epochs):
            try:
                stored = self.manager.item_metadata(step)["state"]
                self._check_structure(step, stored, abstract)
                return self._restore_by_name(step, stored, like)
            except StructureError:
                raise
            except Exception as err:  # TensorStore and Orbax raise many types for a bad file
                reason = f"{type(err).__name__}: {str(err).strip().splitlines()[0][:200]}"
                if i + 1 == len(epochs):
                    raise ValueError(
                        f"no checkpoint in {self.directory} can be read (the last: {reason}); "
                        "delete the folder to train from the start"
                    ) from err
            log.warning(
                "checkpoint %s/%d cannot be read (%s): %s checkpoint %d",
                self.directory,
                step,
                reason,
                "deleted, resuming from" if resuming else "reading",
                epochs[i + 1],
            )
            if resuming:
                self.manager.delete(step)

    def restore_stored(self):
        """(state, meta) of the latest readable checkpoint as stored: nested dicts of NumPy
        arrays named as the state's fields, for a reader that has no state to restore into
        (loading a policy of an older run directory). Never deletes a checkpoint."""
        ocp = _orbax()
        epochs = sorted(self.manager.all_steps(), reverse=True)
        if not epochs:
            raise FileNotFoundError(
                f"no checkpoint in {self.directory}: train first, or point to a run directory "
                "that has a checkpoints/ folder"
            )
        reason = ""
        for step in epochs:
            try:
                stored = self.manager.item_metadata(step)["state"]
                target = jax.tree.map(lambda leaf: np.empty(leaf.shape, leaf.dtype), stored.tree)
                restored = self.manager.restore(
                    step,
                    args=ocp.args.Composite(
                        state=ocp.args.StandardRestore(target), meta=ocp.args.JsonRestore()
                    ),
                )
                return restored.state, restored.meta
            except Exception as err:  # TensorStore and Orbax raise many types for a bad file
                reason = f"{type(err).__name__}: {str(err).strip().splitlines()[0][:200]}"
                log.warning("checkpoint %s/%d cannot be read (%s)", self.directory, step, reason)
        raise ValueError(f"no checkpoint in {self.directory} can be read (the last: {reason})")

    def _restore_by_name(self, step: int, stored, like):
        """Restore into the stored tree's own containers (`stored`: its metadata), then move
        each array to the leaf of `like` of the same name (_check_structure: the names
        match), so a field that holds no arrays does not make older checkpoints unreadable;
        an OPTIONAL array the checkpoint lacks takes `like`'s value."""
        ocp = _orbax()
        by_name = {_name(path): x for path, x in jax.tree.leaves_with_path(like)}
        abstract = {k: ocp.utils.to_shape_dtype_struct(x) for k, x in by_name.items()}
        target = jax.tree.map(lambda leaf: abstract[leaf.name], stored.tree)
        restored = self.manager.restore(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardRestore(target), meta=ocp.args.JsonRestore()
            ),
        )
        arrays = {_name(path): x for path, x in jax.tree.leaves_with_path(restored.state)}
        leaves = [arrays[k] if k in arrays else _value(x) for k, x in by_name.items()]
        return jax.tree.unflatten(jax.tree.structure(like), leaves), restored.meta

    def _check_structure(self, step: int, stored, abstract) -> None:
        """Refuse a checkpoint whose arrays (`stored`: its metadata) are not the state's:
        another configuration's."""
        stored = {leaf.name: tuple(leaf.shape) for leaf in jax.tree.leaves(stored)}
        wanted = {_name(path): tuple(x.shape) for path, x in jax.tree.leaves_with_path(abstract)}
        wanted = {k: v for k, v in wanted.items() if k in stored or not k.startswith(OPTIONAL)}
        if stored != wanted:
            differ = sorted(
                f"{k} {stored.get(k, '(absent)')} -> {wanted.get(k, '(absent)')}"
                for k in stored.keys() | wanted.keys()
                if stored.get(k) != wanted.get(k)
            )
            raise StructureError(
                f"checkpoint {self.directory}/{step} comes from another configuration or "
                f"version of hds: its arrays differ from this run's ({'; '.join(differ[:4])}"
                f"{'; ...' if len(differ) > 4 else ''}): resume with the configuration and "
                "version that wrote it, or start a new run in another directory"
            )

    def close(self) -> None:
        self.manager.close()


class StructureError(ValueError):
    """A checkpoint's arrays are not the restored state's."""


def _value(x):
    """A leaf's value: its own, or zeros of its shape where it is abstract."""
    if isinstance(x, jax.ShapeDtypeStruct):
        return jax.numpy.zeros(x.shape, x.dtype)
    return x


def _name(path) -> str:
    keys = (getattr(k, "name", getattr(k, "key", getattr(k, "idx", k))) for k in path)
    return ".".join(str(k) for k in keys)


@contextlib.contextmanager
def _held_back(logger: logging.Logger):
    """The records `logger` emits inside, held back (for the caller to emit or drop)."""
    held: list[logging.LogRecord] = []

    def hold(record: logging.LogRecord) -> bool:
        held.append(record)
        return False

    logger.addFilter(hold)
    try:
        yield held
    finally:
        logger.removeFilter(hold)


def _disk_full(err: BaseException) -> bool:
    """Whether a save failed on a full disk (TensorStore reports ENOSPC in its message)."""
    while err is not None:
        if getattr(err, "errno", None) == errno.ENOSPC or "No space left on device" in str(err):
            return True
        err = err.__cause__ or err.__context__
    return False
