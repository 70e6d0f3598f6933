"""hds: policy optimization through differentiable simulation, and closing the sim2real gap."""

import os

# XLA's C++ log would clutter every command's console: notices on persistent-cache hits, and on
# AVX-512 CPUs an ERROR line per cache hit that rejects tuning flags (+prefer-no-gather) while
# the entry loads and runs fine (jax-ml/jax#38445). Failures still raise in Python; set
# TF_CPP_MIN_LOG_LEVEL=0 to see the C++ log. Set before any entry point imports jax.
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

__version__ = "0.1.0"
