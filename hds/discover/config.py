"""Configuration of gap discovery: its own keys (`DiscoverConfig`, the `discover:` node) and the
primary config of `python -m hds.discover` (`conf/discover.yaml`), which reuses the run's groups
(env: the simulator compared with the data; real, algo, ...: only for `retrain=true`).

Registered with Hydra's ConfigStore as `discover_schema`, so unknown keys and wrong types fail
at composition; `hds.config.validate` then runs every range check before anything compiles.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from hds.config import Config
from hds.effects.library import LIBRARY


def _in_range(key: str, value: float, lower: float, upper: float = float("inf")) -> None:
    if not lower <= value <= upper:
        raise ValueError(f"{key} = {value} is out of range: it must lie in [{lower}, {upper}]")


@dataclass
class DiscoverConfig:
    # physics backend of the fits: auto = the closed-form analytic backend where it supports
    # the model (it compiles and runs orders of magnitude faster than brax's on CPU and agrees
    # with MuJoCo to float32 round-off), else the env's; env = always the env's; or a name.
    # The corrected config keeps the env's own backend.
    backend: str = "auto"
    heldout_fraction: float = 0.25  # share of episodes held out (selection and reported errors)
    horizon: int = 10  # k: steps of the multi-step (k-step) predictions that are fitted
    stride: int = 1  # a k-step window starts every `stride` steps
    warmup: int = 25  # past actions replayed into stateful effects (delay, lag) before a window
    max_delay: int = 5  # action delays of 1 .. max_delay steps are enumerated; 0: none
    effects: list[str] = field(default_factory=lambda: list(LIBRARY))  # candidate effect types
    max_effects: int = 4  # most effects named
    # Fits of up to b effects at once (the selected ones and a candidate) compile for b slots
    # for each b listed, and for max_effects: fewer sizes, fewer compiles; a slot more costs a
    # forward-mode tangent per iteration.
    slot_buckets: list[int] = field(default_factory=lambda: [3])
    stop_margin: float = 0.05  # an effect must lower held-out error by this share to be added
    min_improvement: float = 1e-3  # ... and by this much (normalized RMSE, signal stds)
    min_share: float = 0.005  # ... and explain at least this share of the original error (MSE)
    iterations: int = 30  # most Levenberg-Marquardt iterations per fit
    # initial state of each fitted window: measured (as recorded), estimated along with the
    # effects (multiple shooting: unbiased under measurement noise, slower), or auto:
    # estimated when the median over variables of the estimated measurement noise exceeds
    # noise_threshold (share of a std): sensor noise shows on every channel, while the kinks
    # of stick-slip friction raise only the velocities' estimates
    initial_state: str = "auto"
    noise_threshold: float = 0.004
    unexplained_warning: float = 0.3  # report a likely missing out-of-library effect above this
    seed: int = 0  # the split of episodes into identification and held-out sets
    bins: int = 8  # bins of each feature when locating where the residual depends on it
    plot_episodes: int = 2  # held-out episodes drawn in the trajectory plot

    def check(self):
        from hds.envs.system import BACKENDS

        if self.backend not in ("auto", "env", *BACKENDS):
            raise ValueError(
                f"discover.backend = {self.backend!r} is not allowed; choose one of "
                f"{['auto', 'env', *BACKENDS]}"
            )
        _in_range("discover.heldout_fraction", self.heldout_fraction, 0.01, 0.9)
        _in_range("discover.horizon", self.horizon, 1)
        _in_range("discover.stride", self.stride, 1)
        _in_range("discover.warmup", self.warmup, 0)
        _in_range("discover.max_delay", self.max_delay, 0, 50)
        _in_range("discover.max_effects", self.max_effects, 0)
        if any(int(b) < 1 for b in self.slot_buckets):
            raise ValueError(
                f"discover.slot_buckets = {list(self.slot_buckets)} must be positive "
                "numbers of effects"
            )
        _in_range("discover.stop_margin", self.stop_margin, 0.0, 1.0)
        _in_range("discover.min_improvement", self.min_improvement, 0.0)
        _in_range("discover.min_share", self.min_share, 0.0, 1.0)
        _in_range("discover.iterations", self.iterations, 1)
        if self.initial_state not in ("auto", "measured", "estimated"):
            raise ValueError(
                f"discover.initial_state = {self.initial_state!r} is not allowed; "
                "choose one of ['auto', 'measured', 'estimated']"
            )
        _in_range("discover.noise_threshold", self.noise_threshold, 0.0)
        _in_range("discover.unexplained_warning", self.unexplained_warning, 0.0, 1.0)
        _in_range("discover.bins", self.bins, 2)
        _in_range("discover.plot_episodes", self.plot_episodes, 0)
        unknown = [e for e in self.effects if e not in LIBRARY]
        if unknown:
            raise ValueError(
                f"discover.effects has unknown effects {unknown}; the library has: "
                f"{', '.join(LIBRARY)}"
            )


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
    discover: DiscoverConfig = field(default_factory=DiscoverConfig)
    emps: EmpsConfig = field(default_factory=EmpsConfig)  # only for .mat (EMPS) files


def register() -> None:
    ConfigStore.instance().store(name="discover_schema", node=DiscoverAppConfig)


register()
