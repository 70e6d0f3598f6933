"""Measured data: the dataset format (the data contract, see `hds.data.format`), excitation
signals for identification, and recording datasets from plants."""

from hds.data.collect import collect, initial_states
from hds.data.excitation import SIGNALS, chirp, excitation, make_rng, prbs, random_steps
from hds.data.format import Dataset, check, concatenate, load, save, split_episodes, validate

__all__ = [
    "SIGNALS",
    "Dataset",
    "check",
    "chirp",
    "concatenate",
    "collect",
    "excitation",
    "initial_states",
    "load",
    "make_rng",
    "prbs",
    "random_steps",
    "save",
    "split_episodes",
    "validate",
]
