"""A run directory's identity: the configuration that produced what it holds, and who uses it.

A run directory with results (checkpoints, a learned model, summary.json) keeps in config.yaml
the configuration that produced them. A run started again on it (to resume, or a sweep started
again) with another configuration is refused before anything compiles, naming the keys that
differ, unless it sets `resume_changed=true`: the run then continues with the new settings,
and the configurations it ran with before are kept as config.<n>.yaml. A finished run
(summary.json) is never recomputed, so it refuses a change either way. Hydra rewrites
.hydra/*.yaml at every start; the files of the accepted configuration are kept in
.hydra/accepted/ and put back when a start is refused.

A run holds a lock on its directory while it runs: a second run started on it is refused at
once (two runs writing one directory's checkpoints corrupt them).
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import logging
import os
import shutil
import sys
import tempfile
import typing
from pathlib import Path

from omegaconf import MISSING, DictConfig, OmegaConf

from hds.config import Config

log = logging.getLogger("hds")

CONFIG = "config.yaml"
LOCK = ".lock"
ACCEPTED = "accepted"  # in .hydra/: Hydra's files of the accepted configuration
RESULTS = ("summary.json", "checkpoints", "dynamics", "discovery")  # what a run leaves behind
# keys that change no result
IGNORED = ("logger", "resume_changed", "threads", "discover.threads")


class RunDirectoryError(ValueError):
    """The run directory is in use, or holds the results of another configuration."""


def check_writable(directory: str | Path, key: str) -> None:
    """Create `directory` and a file in it, or exit with one line naming it and the fix (called
    before Hydra configures its log file there, whose own error hides the path)."""
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as err:
        sys.exit(
            f"error: {key} = {directory} cannot be written ({err.strerror or err}): choose a "
            f"directory you can write to ({key}=<path>), or fix its permissions"
        )


@contextlib.contextmanager
def claim(out_dir: str | Path, cfg: DictConfig, hydra_dir: str | Path | None = None):
    """Lock `out_dir` for this run and check that its results come from `cfg` (the composed
    config; `hydra_dir`: Hydra's .hydra folder of this run, or None). Records `cfg` as the
    directory's configuration when it has none or the change is accepted."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    with open(out_dir / LOCK, "a+") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            _restore_hydra_files(hydra_dir)
            lock.seek(0)
            holder = lock.read().strip() or "another process"
            raise RunDirectoryError(
                f"{out_dir} is in use by another run ({holder}); wait for it to finish, or "
                "start this run in another directory (leave out hydra.run.dir, or give a new one)"
            ) from None
        lock.seek(0)
        lock.truncate()
        lock.write(f"pid {os.getpid()}")
        lock.flush()
        try:
            _check_identity(out_dir, cfg, hydra_dir)
            yield
        finally:
            lock.seek(0)
            lock.truncate()  # the lock itself goes with the file's closing


def differences(before: DictConfig, after: DictConfig, ignored: tuple = ()) -> list[str]:
    """`key: old -> new` for every result-changing key whose value differs (resolved), those
    of IGNORED and `ignored` and those under them aside. A setting this version of hds no
    longer has, or one it added whose value is its default, is no difference: a run
    directory stays resumable across versions."""
    old, new = _flat(before), _flat(after)
    defaults = _flat(_schema_defaults())

    def changed(key):
        if key not in new:
            return False
        if key not in old:
            return new[key] != defaults.get(key, MISSING)
        return old[key] != new[key]

    return [
        f"{key}: {old.get(key, '(absent)')} -> {new[key]}"
        for key in sorted(old.keys() | new.keys())
        if changed(key) and not _under(key, (*IGNORED, *ignored))
    ]


def _under(key: str, prefixes: tuple) -> bool:
    return any(key == p or key.startswith(p + ".") for p in prefixes)


def _schema_defaults() -> DictConfig:
    """Every setting's default, those of the groups (env, real, ...: missing in Config until
    a group option fills them) included."""
    schema = OmegaConf.structured(Config)
    for name, kind in typing.get_type_hints(Config).items():
        if OmegaConf.is_missing(schema, name) and dataclasses.is_dataclass(kind):
            schema[name] = OmegaConf.structured(kind)
    return schema


def _flat(cfg: DictConfig) -> dict[str, object]:
    flat: dict[str, object] = {}

    def walk(node, prefix):
        if isinstance(node, dict) and node:
            for k, v in node.items():
                walk(v, f"{prefix}.{k}" if prefix else str(k))
        else:
            flat[prefix] = node

    walk(OmegaConf.to_container(cfg, resolve=True), "")
    return flat


def _check_identity(out_dir: Path, cfg: DictConfig, hydra_dir: str | Path | None) -> None:
    recorded = out_dir / CONFIG
    has_results = any((out_dir / name).exists() for name in RESULTS)
    if recorded.is_file() and has_results:
        changed = differences(OmegaConf.load(recorded), cfg)
        if not changed:
            return
        finished = (out_dir / "summary.json").is_file()
        if finished or not cfg.get("resume_changed", False):
            _restore_hydra_files(hydra_dir)
            raise RunDirectoryError(_refusal(out_dir, changed, finished))
        log.warning(
            "resume_changed=true: %s continues with another configuration (%s); the one it "
            "ran with so far is kept as %s",
            out_dir,
            "; ".join(changed),
            _keep_previous(recorded).name,
        )
    OmegaConf.save(cfg, recorded, resolve=True)
    if hydra_dir is not None:
        accepted = Path(hydra_dir) / ACCEPTED
        accepted.mkdir(parents=True, exist_ok=True)
        for path in Path(hydra_dir).glob("*.yaml"):
            shutil.copy2(path, accepted / path.name)


def _refusal(out_dir: Path, changed: list[str], finished: bool) -> str:
    what = "finished with" if finished else "was started with"
    fix = "" if finished else ", or add resume_changed=true to continue this one with them"
    return (
        f"{out_dir} holds a run that {what} another configuration; these keys differ: "
        f"{'; '.join(changed)}. Start a new run for the new settings (leave out hydra.run.dir, "
        f"or give a new one){fix}"
    )


def _keep_previous(recorded: Path) -> Path:
    n = 1
    while (previous := recorded.with_name(f"config.{n}.yaml")).exists():
        n += 1
    recorded.replace(previous)
    return previous


def _restore_hydra_files(hydra_dir: str | Path | None) -> None:
    """Put back Hydra's record of the accepted configuration, which this start overwrote."""
    if hydra_dir is None:
        return
    for path in (Path(hydra_dir) / ACCEPTED).glob("*.yaml"):
        shutil.copy2(path, Path(hydra_dir) / path.name)


def optimizing(hydra_cfg) -> bool:
    """Whether a job is a trial of Optuna's sweeper (hydra/sweeper=optuna), whose failed
    trials are recorded as such rather than stopping or failing the sweep."""
    sweeper = hydra_cfg.get("sweeper") or {}
    return str(sweeper.get("_target_", "")).endswith("OptunaSweeper")
