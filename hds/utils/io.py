"""Atomic writes: a result file is either the old one or the complete new one, never half.
Files get a normal file's mode (0644 under the usual umask), and JSON is strict: a non-finite
number is written as null, never as a bare NaN that JSON readers reject, and an object's
`non_finite` key lists where its nulls stood for NaN or inf."""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path


def file_mode() -> int:
    """The mode `open` gives a new file under the process's umask (mkstemp's is 0600)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, file_mode())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def strict_json(obj, where: str = "") -> tuple[object, list[str]]:
    """(obj with every non-finite float replaced by None, the paths of those floats)."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None, [where or "."]
    if isinstance(obj, dict):
        pairs = [(k, strict_json(v, f"{where}.{k}" if where else str(k))) for k, v in obj.items()]
        return {k: v for k, (v, _) in pairs}, [p for _, (_, paths) in pairs for p in paths]
    if isinstance(obj, (list, tuple)):
        items = [strict_json(v, f"{where}[{i}]") for i, v in enumerate(obj)]
        return [v for v, _ in items], [p for _, paths in items for p in paths]
    return obj, []


def atomic_write_json(path: str | Path, obj) -> Path:
    clean, non_finite = strict_json(obj)
    if non_finite and isinstance(clean, dict):
        clean["non_finite"] = non_finite
    return atomic_write_bytes(path, (json.dumps(clean, indent=2, allow_nan=False) + "\n").encode())


def read_json(path: str | Path):
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{path} does not exist") from None
    except json.JSONDecodeError as err:
        raise ValueError(
            f"{path} is not valid JSON ({err}); delete it or rerun to rewrite it"
        ) from None
