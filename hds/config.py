"""Structured config schemas: one dataclass per `conf/` group, registered with Hydra.

Hydra merges the YAML files onto these schemas, so an unknown key or a wrong type fails at
composition. `validate(cfg)` then builds the dataclasses, whose checks reject out-of-range values
with a message naming the key and what is allowed, before anything compiles.
"""

from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from hydra.errors import ConfigCompositionException
from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf
from omegaconf.errors import ConfigAttributeError, ConfigKeyError

from hds.effects import apply as _effects
from hds.effects.library import LIBRARY, check_params, effect_type
from hds.envs.system import BACKENDS, load_spec, resolve_xml, target_names


def _one_of(key: str, value: Any, allowed) -> None:
    if value not in allowed:
        raise ValueError(f"{key} = {value!r} is not allowed; choose one of {list(allowed)}")


def _in_range(key: str, value: float, lower: float, upper: float = float("inf")) -> None:
    if not lower <= value <= upper:
        raise ValueError(f"{key} = {value} is out of range: it must lie in [{lower}, {upper}]")


@dataclass
class EffectConfig:
    name: str = MISSING
    target: str = MISSING
    params: dict[str, float] = field(default_factory=dict)

    def check(self):
        effect_type(self.name)
        check_params(self.name, dict(self.params), where=f"effect {self.name}@{self.target}")


def _effects_field():
    return field(default_factory=list)


@dataclass
class TaskConfig:
    kind: str = "target"  # target: quadratic cost to q_target; reference: the reference project's
    horizon: int = 100
    q_mean: list[float] = MISSING
    q_spread: list[float] = MISSING
    qd_spread: list[float] = MISSING
    q_target: list[float] = MISSING
    q_weight: list[float] = MISSING
    qd_weight: list[float] = MISSING
    effort: float = 0.0

    def check(self):
        _one_of("env.task.kind", self.kind, ("target", "reference"))
        _in_range("env.task.horizon", self.horizon, 1)
        _in_range("env.task.effort", self.effort, 0.0)
        for key in ("q_spread", "qd_spread", "q_weight", "qd_weight"):
            if any(v < 0 for v in getattr(self, key)):
                raise ValueError(f"env.task.{key} = {getattr(self, key)} must be non-negative")


@dataclass
class EnvConfig:
    name: str = MISSING
    xml: str = MISSING  # an asset of hds/envs/assets or a path to any MJCF
    backend: str = "generalized"
    timestep: float = 0.02  # MJCF physics timestep, s
    frames_per_step: int = 2  # env dt = timestep * frames_per_step
    sharpness: float = 50.0  # smoothing of Coulomb friction and dead zones in the simulator
    task: TaskConfig = field(default_factory=TaskConfig)
    effects: list[EffectConfig] = _effects_field()  # effects the simulator already models

    def check(self):
        _one_of("env.backend", self.backend, BACKENDS)
        _in_range("env.timestep", self.timestep, 1e-6, 1.0)
        _in_range("env.frames_per_step", self.frames_per_step, 1)
        _in_range("env.sharpness", self.sharpness, 1e-6)


@dataclass
class RealConfig:
    plant: str = "mujoco"  # mujoco: C MuJoCo, an independent engine; brax: the simulator itself
    friction_gap: float = 1.0  # scales every friction effect below
    effects: list[EffectConfig] = _effects_field()  # the effects the simulator does not know

    def check(self):
        _one_of("real.plant", self.plant, ("mujoco", "brax"))
        _in_range("real.friction_gap", self.friction_gap, 0.0)


@dataclass
class AlgoConfig:
    name: str = "pods"
    order: str = "first"  # first: gradient step; second: Gauss-Newton step
    epochs: int = 30
    rollouts: int = 50  # initial states per epoch
    inner_epochs: int = 20  # regression epochs onto the improved actions
    minibatch: int = 256  # (state, action) pairs per regression step
    learning_rate: float = 1e-3
    step_size: float = 2e-2  # alpha of the action update
    line_search: int = 8  # candidate step sizes alpha / 2^k, k < line_search, evaluated at once
    grad_clip: float = 1e3  # global-norm clip of each action gradient
    gn_damping: float = 1e-3  # Levenberg damping of the Gauss-Newton solve
    improve_steps: int = 1  # action-improvement steps per epoch before regressing (PODS: 1)
    # open_loop (PODS): improve the rollout's controls as an open-loop sequence and regress
    # the policy onto them at the rollout's states; closed_loop: improve perturbations of the
    # policy's own controls through its feedback, and regress onto the improved trajectory
    improve_in: str = "open_loop"
    grad_window: int = 0  # closed loop: SHAC-style truncated gradients, 0 = the whole horizon
    early_stop: float = 0.0  # stop regressing once the loss improves less than this
    hidden: list[int] = field(default_factory=lambda: [64, 64])
    chunk: int = 5  # epochs per compiled chunk, between host-side logs and checkpoints

    def check(self):
        _one_of("algo.order", self.order, ("first", "second"))
        _one_of("algo.improve_in", self.improve_in, ("open_loop", "closed_loop"))
        if self.improve_in == "closed_loop" and self.order != "first":
            raise ValueError(
                "algo.improve_in = closed_loop takes first-order steps only; "
                "choose algo.order=first (or algo.improve_in=open_loop for Gauss-Newton)"
            )
        counts = ("epochs", "rollouts", "inner_epochs", "minibatch", "line_search", "chunk")
        for key in (*counts, "improve_steps"):
            _in_range(f"algo.{key}", getattr(self, key), 1)
        for key in ("learning_rate", "step_size", "grad_clip"):
            _in_range(f"algo.{key}", getattr(self, key), 1e-12)
        _in_range("algo.gn_damping", self.gn_damping, 0.0)
        _in_range("algo.grad_window", self.grad_window, 0)
        if self.grad_window and self.improve_in != "closed_loop":
            raise ValueError(
                "algo.grad_window truncates closed-loop gradients only; "
                "choose algo.improve_in=closed_loop (or algo.grad_window=0)"
            )
        _in_range("algo.early_stop", self.early_stop, 0.0)


@dataclass
class NoiseConfig:
    schedule: str = "none"  # exploration noise on the policy's actions while collecting
    scale: float = 0.0  # initial standard deviation, control units
    decay: float = 0.5  # exponential: sigma <- sigma * decay every epoch
    final: float = 0.0  # linear, cosine: the value reached at the last epoch

    def check(self):
        _one_of("noise.schedule", self.schedule, ("none", "exponential", "linear", "cosine"))
        _in_range("noise.scale", self.scale, 0.0)
        _in_range("noise.decay", self.decay, 0.0, 1.0)
        _in_range("noise.final", self.final, 0.0)


@dataclass
class AnnealConfig:
    kind: str = "line_search"  # line_search: backtracking; simulated: annealed; fixed
    temperature: float = 1.0  # simulated annealing: initial temperature (relative return)
    cooling: float = 0.9  # simulated annealing: temperature <- temperature * cooling per epoch
    step_decay: float = 1.0  # step size <- step size * step_decay per epoch

    def check(self):
        _one_of("anneal.kind", self.kind, ("line_search", "simulated", "fixed"))
        _in_range("anneal.temperature", self.temperature, 0.0)
        _in_range("anneal.cooling", self.cooling, 0.0, 1.0)
        _in_range("anneal.step_decay", self.step_decay, 0.0, 1.0)


@dataclass
class DynamicsConfig:
    model: str = "none"  # none | mlp | ensemble | residual
    beta: float = 0.0  # fraction of rollouts taken through the learned model
    path: str | None = None  # a saved model to reuse instead of training one
    data: str | None = None  # a measured dataset (.npz/.csv) to fit on instead of collecting
    # network and fitting (hds.dynamics)
    hidden: list[int] = field(default_factory=lambda: [128, 128])
    ensemble_size: int = 5  # members of model=ensemble (mlp and residual have one)
    learning_rate: float = 1e-3
    minibatch: int = 256  # transitions per Adam step
    epochs: int = 300  # most passes over the training transitions
    patience: int = 100  # stop after this many epochs without a better validation loss
    val_fraction: float = 0.2  # share of episodes held out for early stopping and metrics
    eval_steps: list[int] = field(default_factory=lambda: [1, 10, 25])  # open-loop k-step errors
    # data collected from the plant when no dataset is given
    episodes: int = 64
    horizon: int = 100  # steps per episode
    excitation: str = "steps"  # steps | chirp | prbs (hds.data.excitation)
    excitation_scale: float = 0.2  # largest amplitude (share of half range), spread over episodes

    def check(self):
        _one_of("dynamics.model", self.model, ("none", "mlp", "ensemble", "residual"))
        _in_range("dynamics.beta", self.beta, 0.0, 1.0)
        if not self.hidden or any(int(w) < 1 for w in self.hidden):
            raise ValueError(
                f"dynamics.hidden = {list(self.hidden)} must be one or more positive layer widths"
            )
        for key in ("ensemble_size", "minibatch", "epochs", "patience", "episodes", "horizon"):
            _in_range(f"dynamics.{key}", getattr(self, key), 1)
        _in_range("dynamics.learning_rate", self.learning_rate, 1e-12)
        _in_range("dynamics.val_fraction", self.val_fraction, 1e-6, 0.9)
        if not self.eval_steps or any(int(k) < 1 for k in self.eval_steps):
            raise ValueError(
                f"dynamics.eval_steps = {list(self.eval_steps)} must be one or "
                "more positive step counts"
            )
        _one_of("dynamics.excitation", self.excitation, ("steps", "chirp", "prbs"))
        _in_range("dynamics.excitation_scale", self.excitation_scale, 1e-6, 1.0)


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
    min_scale_change: float = 0.03  # ... and a gain or mass scale change its quantity this much
    iterations: int = 30  # most Levenberg-Marquardt iterations per fit
    # initial state of each fitted window: measured (as recorded), estimated along with the
    # effects (multiple shooting: unbiased under measurement noise, slower), or auto:
    # estimated when the median over variables of the estimated measurement noise exceeds
    # noise_threshold (share of a std): sensor noise shows on every channel, while the kinks
    # of stick-slip friction raise only the velocities' estimates
    initial_state: str = "auto"
    noise_threshold: float = 0.004
    unexplained_warning: float = 0.3  # report a likely missing out-of-library effect above this
    min_motion: float = 0.05  # warn when a joint with named friction moves in fewer samples
    seed: int = 0  # the split of episodes into identification and held-out sets
    bins: int = 8  # bins of each feature when locating where the residual depends on it
    plot_episodes: int = 2  # held-out episodes drawn in the trajectory plot

    def check(self):
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
        _in_range("discover.min_scale_change", self.min_scale_change, 0.0, 1.0)
        _in_range("discover.iterations", self.iterations, 1)
        if self.initial_state not in ("auto", "measured", "estimated"):
            raise ValueError(
                f"discover.initial_state = {self.initial_state!r} is not allowed; "
                "choose one of ['auto', 'measured', 'estimated']"
            )
        _in_range("discover.noise_threshold", self.noise_threshold, 0.0)
        _in_range("discover.unexplained_warning", self.unexplained_warning, 0.0, 1.0)
        _in_range("discover.min_motion", self.min_motion, 0.0, 1.0)
        _in_range("discover.bins", self.bins, 2)
        _in_range("discover.plot_episodes", self.plot_episodes, 0)
        unknown = [e for e in self.effects if e not in LIBRARY]
        if unknown:
            raise ValueError(
                f"discover.effects has unknown effects {unknown}; the library has: "
                f"{', '.join(LIBRARY)}"
            )


@dataclass
class LoggerConfig:
    wandb: bool = True
    mode: str = "offline"
    project: str = "hds"
    group: str | None = None  # W&B group: runs of one experiment or sweep share it

    def check(self):
        _one_of("logger.mode", self.mode, ("offline", "disabled"))


@dataclass
class SweepConfig:
    """Numeric settings trained together in one program (see `vmap_runs`; sharded across devices
    when there are several), crossed with each other and with the seeds. Empty: not swept."""

    step_size: list[float] = field(default_factory=list)
    noise_scale: list[float] = field(default_factory=list)
    noise_decay: list[float] = field(default_factory=list)  # noise=exponential only
    # real.friction_gap: each run is evaluated on its own plant, and an oracle trains on its
    # own dynamics; a learned model or a corrected simulator needs a multirun instead
    friction_gap: list[float] = field(default_factory=list)
    # dynamics.beta, the share of rollouts through the learned model (dynamics.model != none)
    beta: list[float] = field(default_factory=list)

    def check(self):
        for key, _ in self.items():
            if any(v < 0 for v in getattr(self, key)):
                raise ValueError(f"sweep.{key} = {getattr(self, key)} must be non-negative")
        if any(v > 1 for v in self.beta):
            raise ValueError(f"sweep.beta = {self.beta} must lie in [0, 1]")

    def items(self):
        """(name, values) of the settings swept."""
        names = ("step_size", "noise_scale", "noise_decay", "friction_gap", "beta")
        return [(k, getattr(self, k)) for k in names if getattr(self, k)]


@dataclass
class Config:
    env: EnvConfig = MISSING
    real: RealConfig = MISSING
    algo: AlgoConfig = MISSING
    noise: NoiseConfig = MISSING
    anneal: AnnealConfig = MISSING
    dynamics: DynamicsConfig = MISSING
    logger: LoggerConfig = MISSING
    seed: int = 0
    seeds: int = 1  # seeds trained together, in one program
    # how many runs of the batch (seeds x sweep settings) that program vmaps at a time, the rest
    # looping: null (auto) vmaps them all on GPUs and across devices, one at a time on a single
    # CPU (faster there, and a run's numbers do not depend on the runs beside it); 0: all
    vmap_runs: int | None = None
    name: str = "default"
    # what the policy trains on: nominal (env as configured); corrected (env plus the effects
    # gap discovery names on data measured on the plant: the `discover` node); real (env plus
    # the plant's own effects, friction smoothed: the oracle, the best achievable real return)
    simulator: str = "nominal"
    oracle: bool = True  # with real=brax, also train an oracle beside the run's own policy
    eval_episodes: int = 32  # initial states shared by the simulator and plant evaluations
    # the key of those initial states: one set for every method, seed and job, so that rows
    # compare like for like and a multirun over seeds matches a run of them together
    eval_seed: int = 10_000
    checkpoints_kept: int = 3
    sweep: SweepConfig = field(default_factory=lambda: SweepConfig())
    discover: DiscoverConfig = field(default_factory=DiscoverConfig)

    def uses_model(self) -> bool:
        """Whether some run of the batch takes rollouts through a learned model."""
        return self.dynamics.model != "none" and max([self.dynamics.beta, *self.sweep.beta]) > 0

    def check(self):
        _one_of("simulator", self.simulator, ("nominal", "corrected", "real"))
        if self.sweep.friction_gap and (self.simulator == "corrected" or self.uses_model()):
            raise ValueError(
                "sweep.friction_gap trains every gap in one program, but a learned model "
                f"(dynamics.model = {self.dynamics.model}) or simulator = corrected needs data "
                "measured at each gap: sweep the gap as a multirun instead "
                "(python -m hds.run -m real.friction_gap=0,1,2)"
            )
        if self.sweep.beta and self.dynamics.model == "none":
            raise ValueError(
                "sweep.beta sweeps the share of rollouts through the learned model, but "
                "dynamics.model = none; choose one (dynamics=mlp, or method=hds)"
            )
        if self.sweep.noise_decay and self.noise.schedule != "exponential":
            raise ValueError(
                f"sweep.noise_decay sweeps the exponential schedule's decay, but "
                f"noise.schedule = {self.noise.schedule}; choose noise=exponential"
            )
        _in_range("seeds", self.seeds, 1)
        if self.vmap_runs is not None:
            _in_range("vmap_runs", self.vmap_runs, 0)
        _in_range("eval_episodes", self.eval_episodes, 1)
        _in_range("checkpoints_kept", self.checkpoints_kept, 1)


def register() -> None:
    ConfigStore.instance().store(name="config_schema", node=Config)


def _check_all(node) -> None:
    """Run `check` on every schema in the tree (they cannot be __post_init__: OmegaConf builds
    default instances of the schemas, with missing values, while it composes)."""
    if hasattr(node, "check"):
        node.check()
    children = node if isinstance(node, list) else getattr(node, "__dict__", {}).values()
    for child in children:
        if isinstance(child, list) or hasattr(child, "__dataclass_fields__"):
            _check_all(child)


def _check_effect_targets(config) -> None:
    """Check that env.xml exists, and env.effects and real.effects against its names (the
    model both the simulator and the plants are built from), with the check the builders run
    (hds.effects.apply.check). Compiling the MJCF with MuJoCo takes milliseconds and compiles
    nothing with JAX; it is skipped when no effect is given."""
    env = getattr(config, "env", None)
    if not isinstance(env, EnvConfig):
        return
    real = getattr(config, "real", None)
    groups = [("env.effects", env.effects)]
    if isinstance(real, RealConfig):
        groups.append(("real.effects", real.effects))
    try:
        xml = str(resolve_xml(env.xml))
    except FileNotFoundError as err:
        raise ValueError(f"env.xml: {err}") from None
    if not any(effects for _, effects in groups):
        return
    names = target_names(load_spec(xml).compile())
    for key, effects in groups:
        try:
            _effects.check(effects, names)
        except ValueError as err:
            raise ValueError(f"{key}: {err}") from None


def validate(cfg: DictConfig) -> Config:
    """Build the typed config and run every range check; raise ValueError naming the key."""
    try:
        _check_known_keys(cfg)
    except ValueError as err:
        raise ValueError(f"invalid config: {err}") from None
    try:
        config = OmegaConf.to_object(cfg)
    except Exception as err:  # e.g. a required value left as ???
        raise ValueError(f"invalid config: {err}") from None
    try:
        _check_all(config)
        _check_effect_targets(config)
    except ValueError as err:
        raise ValueError(f"invalid config: {err}") from None
    return config


def allowed_keys_hint(err: Exception) -> str | None:
    """For omegaconf's unknown-key error ("Key 'frictoin' not in 'EnvConfig'"): a line naming
    the node, the keys it allows and the closest of them; None for any other error."""
    if not isinstance(err, (ConfigKeyError, ConfigAttributeError)):
        return None
    node, key = getattr(err, "parent_node", None), getattr(err, "key", None)
    object_type = getattr(err, "object_type", None)
    if dataclasses.is_dataclass(object_type):
        allowed = [f.name for f in dataclasses.fields(object_type)]
    elif isinstance(node, DictConfig):
        allowed = [str(k) for k in node.keys()]
    else:
        return None
    if key is None or str(key) in allowed:
        return None
    full_key = str(getattr(err, "full_key", "") or key)
    return _unknown_key(full_key.rsplit(".", 1)[0] if "." in full_key else "", key, allowed)


def _unknown_key(where: str, key, allowed: list[str]) -> str:
    close = difflib.get_close_matches(str(key), allowed, n=1)
    hint = f"; did you mean '{close[0]}'?" if close else ""
    where = where or "the config"
    return f"{where} has no key '{key}'; its keys are: {', '.join(allowed)}{hint}"


def _check_known_keys(node, where: str = "") -> None:
    """Refuse keys a schema does not have that composition let through (an override forced
    in with `+`, e.g. `+env.frictoin=1`, which OmegaConf.to_object would silently drop)."""
    if isinstance(node, DictConfig):
        schema = OmegaConf.get_type(node)
        keys = [str(k) for k in node.keys()]
        if dataclasses.is_dataclass(schema):
            allowed = [f.name for f in dataclasses.fields(schema)]
            extra = [k for k in keys if k not in allowed]
            if extra:
                raise ValueError(_unknown_key(where, extra[0], allowed))
        children = [(k, node._get_node(k)) for k in keys]
    elif isinstance(node, ListConfig):
        children = [(str(i), node._get_node(i)) for i in range(len(node))]
    else:
        return
    for key, child in children:
        _check_known_keys(child, f"{where}.{key}" if where else key)


def _explain_unknown_keys() -> None:
    """Make Hydra's unknown-key errors list the allowed keys of the node.

    Hydra reports `env.frictoin=1` as "Key 'frictoin' not in 'EnvConfig'". Every composition
    (`python -m hds.run`, `python -m hds.discover`, multiruns, and hydra.compose in tests and
    benchmarks) goes through `ConfigLoaderImpl.load_configuration` (hydra-core 1.3, pinned),
    so that one method is wrapped here: an override or a config file naming an unknown key
    raises a ConfigCompositionException that also names the keys allowed there."""
    from hydra._internal.config_loader_impl import ConfigLoaderImpl

    load = ConfigLoaderImpl.load_configuration
    if getattr(load, "_hds_explains_keys", False):
        return

    def load_configuration(self, *args, **kwargs):
        try:
            return load(self, *args, **kwargs)
        except ConfigCompositionException as err:
            hint = allowed_keys_hint(err.__cause__)
            if hint is None:
                raise
            lines = [line for line in str(err).splitlines() if not line.startswith("To append")]
            raise ConfigCompositionException("\n".join([*lines, hint])) from err.__cause__

    load_configuration._hds_explains_keys = True
    ConfigLoaderImpl.load_configuration = load_configuration


def load_config(path) -> Config:
    """The validated config of a run from its saved config.yaml."""
    schema = OmegaConf.structured(Config)
    return validate(OmegaConf.merge(schema, OmegaConf.load(path)))


register()
_explain_unknown_keys()
