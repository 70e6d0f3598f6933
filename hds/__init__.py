"""hds: policy optimization through differentiable simulation, and closing the sim2real gap."""

__version__ = "0.1.0"
