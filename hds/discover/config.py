"""The primary config of `python -m hds.discover` (`conf/discover.yaml`): a measured dataset and
the run's groups (env: the simulator compared with the data; real, algo, ...: only for
`retrain=true`). Discovery's own keys (`DiscoverConfig`, the `discover:` node) live with the
run's schema in hds.config, since `python -m hds.run simulator=corrected` runs discovery too.

Registered with Hydra's ConfigStore as `discover_schema`, so unknown keys and wrong types fail
at composition; `hds.config.validate` then runs every range check before anything compiles.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from hds.config import Config, DiscoverConfig, _in_range
from hds.effects.library import effect_type

__all__ = ["DiscoverAppConfig", "DiscoverConfig", "EmpsConfig"]


@dataclass
class EmpsConfig:
    """How an EMPS .mat record becomes a dataset (hds.data.emps.load)."""

    dt: float = 0.005  # s between observations (the record is 1 kHz; a multiple of 1 ms)
    segment: float = 1.0  # s per episode
    cutoff: float = 100.0  # Hz, the Butterworth low-pass before differentiating
    order: int = 4

    def check(self):
        _in_range("emps.dt", self.dt, 1e-3, 1.0)
        _in_range("emps.segment", self.segment, self.dt)
        _in_range("emps.cutoff", self.cutoff, 1e-3, 0.5 / 1e-3)
        _in_range("emps.order", self.order, 1, 10)


@dataclass
class DiscoverAppConfig(Config):
    """`python -m hds.discover`: a measured dataset and the simulator it is compared with."""

    data: str = MISSING  # the measured dataset (.npz, .csv; .mat: EMPS, see hds.data.emps)
    validation: str | None = None  # another dataset whose errors are reported, never fitted
    retrain: bool = False  # train PODS on the original and the corrected simulator, evaluate
    # both on the plant of `real` (the one that produced the data)
    emps: EmpsConfig = field(default_factory=EmpsConfig)  # only for .mat (EMPS) files

    def check(self):
        super().check()
        if self.retrain and not plant_has_effects(self.real):
            raise ValueError(
                f"retrain = true evaluates both policies on the plant of `real`, the one that "
                f"produced the data, but that plant has no effect (real.plant = "
                f"{self.real.plant}, real.effects = {[e.name for e in self.real.effects]}, "
                f"real.friction_gap = {self.real.friction_gap}): the gap before and after "
                "would be measured on the nominal model. Give the plant the data came from, "
                "e.g. real=mujoco 'real.effects=[{name: coulomb_friction, target: slider, "
                "params: {force: 20}}]' (a dataset read from a file, e.g. measured on "
                "hardware, does not tell hds its plant: it must be given this way), or drop "
                "retrain=true"
            )


def plant_has_effects(real) -> bool:
    """Whether a `real` config's plant differs from the nominal model: some effect that is not
    friction, or friction not scaled to zero by real.friction_gap."""
    return any(not effect_type(e.name).friction or real.friction_gap > 0 for e in real.effects)


def register() -> None:
    ConfigStore.instance().store(name="discover_schema", node=DiscoverAppConfig)


register()
