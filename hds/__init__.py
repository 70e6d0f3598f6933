"""hds: policy optimization through differentiable simulation, and closing the sim2real gap.

The Python API (docs/tutorials/python.md); each name is imported on first use, so `import hds`
stays light for the command-line entry points:

    cfg = hds.compose(["method=pods_cl", "seeds=3"])      # a validated Config, no CLI needed
    result = hds.train(cfg)                                # a Result: rows, histories, run_dir
    policy = hds.load_policy(result.run_dir, seed=0)       # u = policy(obs)
    hds.evaluate_policy(policy, real=hds.compose(["real.friction_gap=2"]).real).mean_ci()
    hds.export_policy(policy, "exported/")                 # runs without JAX
"""

import importlib
import os
import warnings

from omegaconf import OmegaConf

# XLA's C++ log would clutter every command's console: notices on persistent-cache hits, and on
# AVX-512 CPUs an ERROR line per cache hit that rejects tuning flags (+prefer-no-gather) while
# the entry loads and runs fine (jax-ml/jax#38445). Failures still raise in Python; set
# TF_CPP_MIN_LOG_LEVEL=0 to see the C++ log. Set before any entry point imports jax.
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

# `${hds.once:${name}}`: the value its first resolution gave. OmegaConf caches a resolver's result
# by the text of its arguments and Hydra copies the sweep's cache into every job's config, so the
# sweep directory (conf/config.yaml) names the sweep's name in every job, though a job with
# another method has another name: all jobs land in the one sweep directory.
OmegaConf.register_new_resolver("hds.once", lambda value: value, use_cache=True, replace=True)

__version__ = "0.1.0"

_API = {  # public name: (module, attribute)
    "compose": ("hds.config", "compose"),
    "Config": ("hds.config", "Config"),
    "train": ("hds.experiment", "run"),
    "Hooks": ("hds.experiment", "Hooks"),
    "Result": ("hds.experiment", "Result"),
    "load_policy": ("hds.policy", "load_policy"),
    "Policy": ("hds.policy", "Policy"),
    "evaluate_policy": ("hds.policy", "evaluate_policy"),
    "export_policy": ("hds.policy", "export_policy"),
}
__all__ = list(_API)
# the API's names until 2026-11-27, kept working with a DeprecationWarning: `hds.evaluate` and
# `hds.export` are the commands' modules (`python -m hds.evaluate`), and importing one of them
# makes it the attribute of that name, so the functions took names of their own
_DEPRECATED = {"evaluate": "evaluate_policy", "export": "export_policy"}


def __dir__() -> list[str]:
    """The lazy API names beside the module's own (tab completion, dir(hds))."""
    return sorted(set(globals()) | set(_API))


def __getattr__(name: str):
    if name in _DEPRECATED:
        warnings.warn(
            f"hds.{name} is deprecated: use hds.{_DEPRECATED[name]}", DeprecationWarning, 2
        )
        name = _DEPRECATED[name]
    if name not in _API:
        raise AttributeError(f"module 'hds' has no attribute '{name}'")
    module, attribute = _API[name]
    return getattr(importlib.import_module(module), attribute)
