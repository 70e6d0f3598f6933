"""hds: policy optimization through differentiable simulation, and closing the sim2real gap."""

import os

# XLA's C++ notices (e.g. on persistent-cache hits) would clutter every command's console;
# set before any entry point imports jax.
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")

__version__ = "0.1.0"
