"""The simulator kinds a config may name (`simulator=`): the one list of their names, and what
the checks need to know of each before anything heavy is imported.

A kind's class (`hds.simulators`: what builds a method's training simulator) imports JAX and
brax. The config validates `simulator=`, and the command line checks a run's data, before any
of that is imported: so each kind is declared here by name, with where its class lives
(imported when a run builds its simulator: `hds.simulators.load`) and the light facts the
checks read. A kind defined in another module is declared by `hds.simulators.register` when
that module is imported (import it before composing a config that names the kind).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Kind:
    name: str  # the config's simulator= value
    where: str  # "module:Class" of its hds.simulators.SimulatorKind
    # built by gap discovery on data measured on the plant: that data's size is checked before
    # the run (hds.data.budget), and the batch measures one plant (no swept friction gap)
    discovers: bool = False


KINDS: dict[str, Kind] = {}


def declare(name: str, where: str, discovers: bool = False) -> Kind:
    """Add a kind to the names a config accepts; the same name from another class is refused."""
    known = KINDS.get(name)
    if known is not None and known.where != where:
        raise ValueError(
            f"simulator kind {name!r} is registered twice: {known.where} and {where}; "
            "give the new kind another name"
        )
    KINDS[name] = Kind(name, where, discovers)
    return KINDS[name]


def kind(name: str) -> Kind:
    """The declared kind of this name (a one-line error naming the kinds there are)."""
    if name not in KINDS:
        raise ValueError(
            f"simulator = {name!r} is not a registered kind; choose one of {sorted(KINDS)}"
        )
    return KINDS[name]


# what a method trains on (docs/simulators.md): the env as configured; the env plus what gap
# discovery names on plant data; the plant's own effects (the oracle); domain randomization
declare("nominal", "hds.simulators:Nominal")
declare("corrected", "hds.simulators:Corrected", discovers=True)
declare("real", "hds.simulators:Real")
declare("randomized", "hds.simulators:Randomized")
