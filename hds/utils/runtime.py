"""Process-wide JAX set-up: the persistent compilation cache (a second process skips compiling)."""

from __future__ import annotations

import os
from pathlib import Path

import jax

DEFAULT_CACHE = Path(os.environ.get("HDS_JAX_CACHE", Path.home() / ".cache" / "hds" / "jax"))


def enable_compilation_cache(path: str | Path | None = None) -> Path:
    path = Path(path or DEFAULT_CACHE).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
