"""hds: policy optimization through differentiable simulation, and closing the sim2real gap."""

import os

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
