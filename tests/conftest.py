"""Shared fixtures. JAX compiles are the main cost on CPU: build each env and compile each
function once per session (session-scoped fixtures), with the persistent compilation cache on."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")

from hds.config import compose  # noqa: E402
from hds.utils.runtime import enable_compilation_cache  # noqa: E402

enable_compilation_cache()

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
SHARED = ROOT.parent / "shared"


def make_config(*overrides: str, config_name: str = "config"):
    """Compose a primary config (conf/config.yaml: `python -m hds.run`; conf/discover.yaml:
    `python -m hds.discover`) with overrides and validate it, as the command does."""
    return compose(list(overrides), config_name)


def trained(*args, **kwargs):
    """(params, history) of hds.experiment.train(*args, **kwargs)."""
    from hds.experiment import train

    training = train(*args, **kwargs)
    return training.params, training.history


@pytest.fixture(scope="session")
def cartpole_cfg():
    return make_config().env


@pytest.fixture(scope="session")
def cartpole_env(cartpole_cfg):
    from hds.envs import make_env

    return make_env(cartpole_cfg)
