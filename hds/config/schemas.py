"""Structured config schemas: one dataclass per `conf/` group, registered with Hydra.

Hydra merges the YAML files onto these schemas, so an unknown key or a wrong type fails at
composition; each schema's `check()` rejects out-of-range values with a message naming the key
and what is allowed (`hds.config.validation.validate` runs them all, before anything compiles).

Importing the schemas imports neither JAX nor MuJoCo: the effect library and the simulator's
backends (which do) are imported when a check runs, so that reading a config, a run's report
or the documentation stays light.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from hds.config import kinds

SEED_MAX = 2**31 - 1  # seeds go into int32 arrays (JAX's PRNG keys, the batch's seed vector)


def _effects_library():
    """hds.effects.library, imported when a check needs it (it imports JAX)."""
    from hds.effects import library

    return library


def _backends() -> tuple[str, ...]:
    """The simulator's physics backends (hds.envs.system imports JAX and MuJoCo)."""
    from hds.envs.system import BACKENDS

    return BACKENDS


# discover.effects' default: the effect library's candidates not marked opt-in
# (hds.effects.library.default_candidates), written out as plain data so that registering the
# schemas (on `import hds.config`) imports no JAX; tests/test_config.py keeps the two the same
DISCOVER_EFFECTS = (
    "coulomb_friction",
    "viscous_damping",
    "actuator_gain",
    "actuator_offset",
    "actuator_deadzone",
    "action_delay",
    "actuator_lag",
    "mass_scale",
    "sensor_bias",
)


def _one_of(key: str, value: Any, allowed) -> None:
    if value not in allowed:
        raise ValueError(f"{key} = {value!r} is not allowed; choose one of {list(allowed)}")


def _in_range(key: str, value: float, lower: float, upper: float = float("inf")) -> None:
    if not lower <= value <= upper:
        raise ValueError(f"{key} = {value} is out of range: it must lie in [{lower}, {upper}]")


def _check_widths(key: str, widths, fewest: int) -> None:
    if len(widths) < fewest or any(int(w) < 1 for w in widths):
        many = "one or more" if fewest else "zero or more"
        raise ValueError(f"{key} = {list(widths)} must be {many} positive layer widths")


@dataclass
class EffectConfig:
    name: str = MISSING
    target: str = MISSING
    params: dict[str, float] = field(default_factory=dict)

    def check(self):
        library = _effects_library()
        library.effect_type(self.name)
        library.check_params(
            self.name, dict(self.params), where=f"effect {self.name}@{self.target}"
        )


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
    # the angles the cost reads: each joint's own (joint), or each link's in the world (world:
    # a hinge on a link that turns about a parallel hinge adds that hinge's angle), so that
    # bending an acrobot's elbow is not a cost of its own and hanging is no local optimum
    angles: str = "joint"
    # the mean return from which a policy counts as solving the task (brax's PPO reaches -26
    # on balance, -485 on swing-up: bench/RESULTS.md); null: no such line
    solved_at: float | None = None

    def check(self):
        _one_of("env.task.kind", self.kind, ("target", "reference"))
        _in_range("env.task.horizon", self.horizon, 1)
        _in_range("env.task.effort", self.effort, 0.0)
        _one_of("env.task.angles", self.angles, ("joint", "world"))
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
    # Coulomb friction's gradient taken from tanh(k v) at this sharpness while its value stays
    # at env.sharpness (a surrogate gradient, hds.effects.friction.friction_direction); null: off
    gradient_sharpness: float | None = None
    task: TaskConfig = field(default_factory=TaskConfig)
    effects: list[EffectConfig] = _effects_field()  # effects the simulator already models

    def check(self):
        _one_of("env.backend", self.backend, _backends())
        _in_range("env.timestep", self.timestep, 1e-6, 1.0)
        _in_range("env.frames_per_step", self.frames_per_step, 1)
        _in_range("env.sharpness", self.sharpness, 1e-6)
        if self.gradient_sharpness is not None:
            _in_range("env.gradient_sharpness", self.gradient_sharpness, 1e-6)


@dataclass
class RealConfig:
    plant: str = "mujoco"  # mujoco: C MuJoCo, an independent engine; brax: the simulator itself
    friction_gap: float = 1.0  # scales every friction effect below
    effects: list[EffectConfig] = _effects_field()  # the effects the simulator does not know
    name: str = ""  # the plant's name in rows and reports (empty: its effects, e.g. gain@slide)
    # a lab plant (hds.real.lab): draw `draw` of this family's distribution, whose effects
    # come first in `effects` (an effect given there that the draw has is the draw's)
    family: str = ""
    draw: int = 0

    def __post_init__(self):
        if self.family:  # idempotent: dataclasses.replace builds it again from its own effects
            from hds.real import lab

            drawn = lab.effects(self.family, self.draw)
            keys = {(e["name"], e["target"]) for e in drawn}
            own = [e for e in self.effects if (e.name, e.target) not in keys]
            self.effects = [EffectConfig(**e) for e in drawn] + own

    def label(self) -> str:
        if not self.name and self.family:
            return f"{self.family}#{self.draw}"
        return self.name or "+".join(f"{e.name}@{e.target}" for e in self.effects) or "none"

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
    # the policy a run returns: the last iterate, or the one whose simulator return was best
    # once the continuation (anneal.effect_ramp) had reached its end
    keep: str = "last"

    def check(self):
        _one_of("algo.order", self.order, ("first", "second"))
        _one_of("algo.keep", self.keep, ("last", "best"))
        _check_widths("algo.hidden", self.hidden, fewest=0)
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
    # [begin, end] shares of the epochs: the simulator's effects are nominal (off) and no
    # rollout runs through a learned model before begin; both grow linearly to their values
    # (effects, dynamics.beta) at end (a continuation); [0, 0]: off
    effect_ramp: list[float] = field(default_factory=lambda: [0.0, 0.0])
    # the ramp waits (at most until it would end on the last epoch) for the policy to solve
    # the task without the effects (a training return >= env.task.solved_at in `solved_for`
    # epochs in a row; a task without one ramps on time): a seed still learning at `begin`
    # would otherwise meet them unready and may never learn. One epoch's return is noisy, but
    # 5 in a row cost more than they saved in the study (experiments/sim2real_friction)
    ramp_when_solved: bool = True
    solved_for: int = 1
    # once under way, the ramp stands still in every epoch whose training return misses
    # env.task.solved_at (still at most until it would end on the last epoch): the effects
    # grow only while the policy copes with them, as automatic domain randomization widens
    # its ranges (OpenAI et al. 2019); a seed that a step of the ramp throws off relearns the
    # task where it stands instead of meeting ever stronger effects
    ramp_pauses: bool = False
    # a horizon curriculum: the action improvement sees only the first `horizon_start` steps
    # of each rollout at the first epoch, then a horizon growing linearly to the task's whole
    # one at the share `horizon_full_at` of the epochs (0: the whole horizon from the start).
    # On a fast unstable system (the Furuta pendulum falls in 0.3 s) the gradient of a long
    # horizon leads to whirling the pendulum over, a local optimum, where a short one teaches
    # the policy to catch it first; with that feedback, longer horizons stay well conditioned
    horizon_start: int = 0
    horizon_full_at: float = 0.5

    def check(self):
        _one_of("anneal.kind", self.kind, ("line_search", "simulated", "fixed"))
        if len(self.effect_ramp) != 2 or not 0 <= self.effect_ramp[0] <= self.effect_ramp[1] <= 1:
            raise ValueError(
                f"anneal.effect_ramp = {list(self.effect_ramp)} must be [begin, end] shares "
                "of the epochs with 0 <= begin <= end <= 1"
            )
        _in_range("anneal.temperature", self.temperature, 0.0)
        _in_range("anneal.cooling", self.cooling, 0.0, 1.0)
        _in_range("anneal.step_decay", self.step_decay, 0.0, 1.0)
        _in_range("anneal.solved_for", self.solved_for, 1)
        if self.ramp_pauses and not self.ramp_when_solved:
            raise ValueError(
                "anneal.ramp_pauses = true needs anneal.ramp_when_solved = true: the ramp "
                "pauses once it is under way, from the epoch the policy first solves the task"
            )
        _in_range("anneal.horizon_start", self.horizon_start, 0)
        _in_range("anneal.horizon_full_at", self.horizon_full_at, 0.0, 1.0)


@dataclass
class DynamicsConfig:
    model: str = "none"  # none | mlp | ensemble | residual
    beta: float = 0.0  # fraction of rollouts taken through the learned model
    # 0: the model's rollouts start from the task's initial states and run the whole horizon;
    # n: each is cut into short ones of n steps (the largest divisor of the horizon not above
    # n) started from states the simulator's rollouts visited (MBPO's branched rollouts)
    branch: int = 0
    # residual: what the policy's gradient takes from the model's rollouts. model: the whole
    # step's derivatives, the network's included; simulator: the network's correction moves the
    # states they visit, the gradient is the simulator's own along them (the network is fitted
    # to predict the plant, not its derivatives: docs/dynamics.md, "What the gradient sees")
    gradient: str = "model"
    path: str | None = None  # a saved model to reuse instead of training one
    data: str | None = None  # a measured dataset (.npz/.csv) to fit on instead of collecting
    # network and fitting (hds.dynamics)
    hidden: list[int] = field(default_factory=lambda: [128, 128])  # widths (silu)
    ensemble_size: int = 5  # members of model=ensemble (mlp and residual have one)
    learning_rate: float = 1e-3
    minibatch: int = 256  # transitions per Adam step
    epochs: int = 300  # most passes over the training transitions
    # stop after this many epochs without a better validation loss (its curve can rise for a
    # while and fall again: keep this generous)
    patience: int = 100
    val_fraction: float = 0.2  # share of episodes held out for early stopping and metrics
    eval_steps: list[int] = field(default_factory=lambda: [1, 10, 25])  # open-loop k-step errors
    # train through a fitted model only if it predicts the held-out plant episodes better than
    # the simulator alone at every k of eval_steps; a model that does not has nothing to add to
    # the simulator it is meant to correct (a delay it cannot represent), and its share is 0
    require_better: bool = True
    # data collected from the plant when no dataset is given
    episodes: int = 64
    horizon: int = 100  # steps per episode
    excitation: str = "steps"  # steps | chirp | prbs (hds.data.excitation)
    # largest amplitude (share of the half range), spread evenly over the episodes; near 1 the
    # cart-pole slams into its rail limits
    excitation_scale: float = 0.2
    # most recorded steps (episodes x steps) a model is fitted on; more is refused before it is
    # processed, with its memory and time (hds.data.budget): window or resample the data
    max_steps: int = 1_000_000

    def check(self):
        _one_of("dynamics.model", self.model, ("none", "mlp", "ensemble", "residual"))
        _one_of("dynamics.gradient", self.gradient, ("model", "simulator"))
        if self.gradient == "simulator" and self.model not in ("none", "residual"):
            raise ValueError(
                f"dynamics.gradient = simulator needs a simulator under the model, but "
                f"dynamics.model = {self.model}: use dynamics=residual, or dynamics.gradient=model"
            )
        _in_range("dynamics.beta", self.beta, 0.0, 1.0)
        _in_range("dynamics.branch", self.branch, 0)
        _check_widths("dynamics.hidden", self.hidden, fewest=1)
        for key in ("ensemble_size", "minibatch", "epochs", "patience", "episodes", "horizon"):
            _in_range(f"dynamics.{key}", getattr(self, key), 1)
        _in_range("dynamics.max_steps", self.max_steps, 1)
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
    effects: list[str] = field(default_factory=lambda: list(DISCOVER_EFFECTS))  # candidates
    max_effects: int = 4  # most effects named
    # Fits of up to b effects at once (the selected ones and a candidate) compile for b slots
    # for each b listed, and for max_effects: fewer sizes, fewer compiles; a slot more costs a
    # forward-mode tangent per iteration.
    slot_buckets: list[int] = field(default_factory=lambda: [3])
    stop_margin: float = 0.05  # an effect must lower held-out error by this share to be added
    min_improvement: float = 1e-3  # ... and by this much (normalized RMSE, signal stds)
    # ... and a gain or mass scale change its quantity by more than the step's implicit damping
    # could (h b / M, hds.discover.explain.scale_margin) and by at least this much
    min_scale_change: float = 0.0
    iterations: int = 30  # most Levenberg-Marquardt iterations per fit
    # fits run at once on threads, as the runs of a batch are (`threads` of the run): 0 = one
    # per core this process may use on a CPU. The numbers do not depend on it
    threads: int = 0
    # initial state of each fitted window: measured (as recorded), estimated along with the
    # effects (multiple shooting: unbiased under measurement noise, slower), or auto:
    # estimated when the median over variables of the estimated measurement noise exceeds
    # noise_threshold (share of a std): sensor noise shows on every channel, while the kinks
    # of stick-slip friction raise only the velocities' estimates; where instead a velocity
    # disagrees with its coordinate's change by more than noise_threshold (a smooth error:
    # de-noised offline, late, biased), both starts are run and the held-out episodes choose
    # (hds.discover.workflow.choose_initial_states)
    initial_state: str = "auto"
    noise_threshold: float = 0.004
    unexplained_warning: float = 0.3  # report a likely missing out-of-library effect above this
    min_motion: float = 0.05  # warn when a joint with named friction moves in fewer samples
    seed: int = 0  # the split of episodes into identification and held-out sets
    bins: int = 8  # bins of each feature when locating where the residual depends on it
    plot_episodes: int = 2  # held-out episodes drawn in the trajectory plot
    # most recorded steps (episodes x steps) discovery takes on; larger data is refused before
    # it is processed, with its memory and time (hds.data.budget): window or resample it
    max_steps: int = 200_000
    # the loop's excitation episodes (hds.loop): steps = random steps (amplitude doubled while
    # the data cannot identify a candidate); designed = each round optimises them through the
    # corrected simulator for the effects below (hds.discover.design, docs/design.md), random
    # steps the fallback where no design keeps the limits
    excitation: str = "steps"
    design_effects: list[str] = field(default_factory=lambda: ["coulomb_friction", "actuator_gain"])

    def check(self):
        if self.excitation not in ("steps", "designed"):
            raise ValueError(
                f"discover.excitation = {self.excitation!r} is not allowed; choose 'steps' "
                "(random steps) or 'designed' (hds.discover.design)"
            )
        if self.backend not in ("auto", "env", *_backends()):
            raise ValueError(
                f"discover.backend = {self.backend!r} is not allowed; choose one of "
                f"{['auto', 'env', *_backends()]}"
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
        _in_range("discover.threads", self.threads, 0)
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
        _in_range("discover.seed", self.seed, 0, SEED_MAX)
        _in_range("discover.max_steps", self.max_steps, 1)
        candidates = _effects_library().candidate_effects()
        unknown = [e for e in [*self.effects, *self.design_effects] if e not in candidates]
        if unknown:
            raise ValueError(
                f"discover.effects or discover.design_effects has unknown or non-candidate "
                f"effects {unknown}; the "
                f"candidates are: {', '.join(candidates)}"
            )


@dataclass
class RangedEffectConfig:
    name: str = MISSING
    target: str = MISSING
    ranges: dict[str, list[Any]] = field(default_factory=dict)  # param: [low, high]

    def check(self):
        where = f"dr.effects {self.name}@{self.target}"
        library = _effects_library()
        etype = library.effect_type(self.name)
        if not self.ranges:
            raise ValueError(f"{where}.ranges is empty; give each parameter a [low, high] range")
        for param, bounds in self.ranges.items():
            numbers = all(isinstance(b, (int, float)) for b in bounds)
            if len(bounds) != 2 or not numbers or bounds[0] > bounds[1]:
                raise ValueError(f"{where}.ranges.{param} = {list(bounds)} must be [low, high]")
            if param in [p.name for p in etype.params if p.discrete]:
                raise ValueError(
                    f"{where}.ranges.{param}: a discrete parameter sets the simulator's shape "
                    "and cannot be drawn per rollout; remove its range"
                )
        for end in (0, 1):  # both ends must be valid values (names, bounds)
            library.check_params(
                self.name, {k: v[end] for k, v in self.ranges.items()}, where=where
            )


@dataclass
class DRConfig:
    """Domain randomization (simulator = randomized, method=dr): every rollout draws the
    parameters of these effects uniformly from their ranges; the simulator's own effects
    (env.effects) keep their values. Its sim return is taken at the ranges' midpoints."""

    effects: list[RangedEffectConfig] = field(default_factory=list)


@dataclass
class LoggerConfig:
    wandb: bool = True
    mode: str = "offline"
    project: str = "hds"
    group: str | None = None  # W&B group: runs of one experiment or sweep share it

    def check(self):
        _one_of("logger.mode", self.mode, ("offline", "disabled"))


SWEEP_KEYS = ("step_size", "noise_scale", "noise_decay", "friction_gap", "beta")


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
        return [(k, getattr(self, k)) for k in SWEEP_KEYS if getattr(self, k)]


@dataclass
class LoopConfig:
    """`python -m hds.loop`: deploy, record, discover, retrain (hds/loop.py)."""

    rounds: int = 2  # correction rounds after round 0 (the loop may stop earlier)
    deploy_episodes: int = 16  # episodes of the current policy recorded on the plant a round
    excitation_episodes: int = 16  # open-loop excitation episodes a round (dynamics.excitation)
    epochs: int = 0  # epochs of each round after the first; 0: algo.epochs
    # each later round starts from the previous round's policy; false: from scratch, as round
    # 0 (a swing-up learned without friction is a way of swinging that warm-started rounds
    # do not leave: experiments/sim2real_friction/README.md)
    warm_start: bool = True
    # a finished run whose training is round 0's (hds.run on the nominal simulator, same
    # settings, no learned model; e.g. a sweep's raw-simulator job): round 0 restores its
    # policies and evaluates them on this loop's plant instead of training them again
    start_from: str | None = None

    def check(self):
        _in_range("loop.rounds", self.rounds, 0)
        _in_range("loop.deploy_episodes", self.deploy_episodes, 1)
        _in_range("loop.excitation_episodes", self.excitation_episodes, 1)
        _in_range("loop.epochs", self.epochs, 0)


@dataclass
class PathsConfig:
    shared: str = "../shared"  # data beside the repository (conf/paths/default.yaml)
    outputs: str = "outputs"  # run and sweep directories


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
    # runs of a batch trained at once on threads, each calling the one compiled program (a
    # run's numbers do not depend on it): 0 = one per core this process may use on a CPU
    # (XLA runs a run's loops on one core), one on an accelerator
    threads: int = 0
    name: str = "default"
    # what the policy trains on: nominal (env as configured); corrected (env plus the effects
    # gap discovery names on data measured on the plant: the `discover` node); real (env plus
    # the plant's own effects, friction smoothed: the oracle, the best achievable real return);
    # randomized (env plus the effects of `dr`, drawn per rollout: domain randomization)
    simulator: str = "nominal"
    oracle: bool = True  # with real=brax, also train an oracle beside the run's own policy
    eval_episodes: int = 32  # initial states shared by the simulator and plant evaluations
    # further plants every policy is also evaluated on (rows per plant): a policy that does not
    # depend on the plant (trained on the nominal or a randomized simulator) trained once for
    # a family of plants. Compose them from conf/real/: defaults `- /real@eval_plants.gain: gain`
    eval_plants: dict[str, RealConfig] = field(default_factory=dict)
    # the key of those initial states: one set for every method, seed and job, so that rows
    # compare like for like and a multirun over seeds matches a run of them together
    eval_seed: int = 10_000
    # draw each method's first policy on its simulator beside the plant (one evaluation
    # episode) into plots/<method>_sim_vs_real.gif, and log it to W&B
    gif: bool = False
    checkpoints_kept: int = 3
    # what `python -m hds.run` returns to Hydra's sweeper (hydra/sweeper=optuna maximizes it):
    # the mean over the runs of their real_return, or of their sim_return (tuning without the
    # plant's returns)
    objective: str = "real_return"
    # continue a run directory whose run had another configuration (hds/rundir.py refuses
    # that otherwise): the epochs before and after the change ran with different settings
    resume_changed: bool = False
    sweep: SweepConfig = field(default_factory=lambda: SweepConfig())
    discover: DiscoverConfig = field(default_factory=DiscoverConfig)
    dr: DRConfig = field(default_factory=DRConfig)
    paths: PathsConfig = field(default_factory=PathsConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)

    def runs(self) -> list[dict]:
        """The runs trained together: every seed crossed with every setting of `sweep`, each
        as {"seed": ..., <swept key>: <value>, ...}."""
        names, values = zip(*self.sweep.items()) if self.sweep.items() else ((), ())
        settings = [dict(zip(names, combo)) for combo in itertools.product(*values)]
        return [{"seed": self.seed + i, **s} for s in settings for i in range(self.seeds)]

    def uses_model(self) -> bool:
        """Whether some run of the batch takes rollouts through a learned model."""
        return self.dynamics.model != "none" and max([self.dynamics.beta, *self.sweep.beta]) > 0

    def check(self):
        _one_of("simulator", self.simulator, tuple(kinds.KINDS))
        _one_of("objective", self.objective, ("real_return", "sim_return"))
        if self.simulator == "randomized" and not self.dr.effects:
            raise ValueError(
                "simulator = randomized (method=dr) draws effect parameters from dr.effects, "
                "which is empty; give one, e.g. dr.effects=[{name: coulomb_friction, target: "
                "slider, ranges: {force: [0, 80]}}]"
            )
        discovers = kinds.kind(self.simulator).discovers
        if self.sweep.friction_gap and (discovers or self.uses_model()):
            built_from_data = "/".join(k.name for k in kinds.KINDS.values() if k.discovers)
            raise ValueError(
                "sweep.friction_gap trains every gap in one program, but a learned model "
                f"(dynamics.model = {self.dynamics.model}) or simulator = {built_from_data} "
                "needs data measured at each gap: sweep the gap as a multirun instead "
                "(python -m hds.run -m real.friction_gap=0,1,2)"
            )
        if self.sweep.beta and self.dynamics.model == "none":
            raise ValueError(
                "sweep.beta sweeps the share of rollouts through the learned model, but "
                "dynamics.model = none; choose one (dynamics=mlp, or method=hds)"
            )
        beta = max([self.dynamics.beta, *self.sweep.beta])  # above 1: sweep's own error
        if (
            self.dynamics.branch
            and self.uses_model()
            and beta <= 1
            and round(beta * self.algo.rollouts) >= self.algo.rollouts
        ):
            raise ValueError(
                f"dynamics.branch = {self.dynamics.branch} starts the model's rollouts from "
                f"states of the simulator's, but a beta of {beta:g} leaves none of "
                f"algo.rollouts = {self.algo.rollouts} on the simulator; lower dynamics.beta "
                "(sweep.beta) or set dynamics.branch=0"
            )
        if self.sweep.noise_decay and self.noise.schedule != "exponential":
            raise ValueError(
                f"sweep.noise_decay sweeps the exponential schedule's decay, but "
                f"noise.schedule = {self.noise.schedule}; choose noise=exponential"
            )
        _in_range("seeds", self.seeds, 1)
        _in_range("seed", self.seed, 0, SEED_MAX - (self.seeds - 1))  # seeds seed .. seed+seeds-1
        _in_range("eval_seed", self.eval_seed, 0, SEED_MAX)
        horizon = self.env.task.horizon
        if self.algo.grad_window > horizon:
            raise ValueError(
                f"algo.grad_window = {self.algo.grad_window} is longer than the task's horizon "
                f"(env.task.horizon = {horizon}); give at most {horizon}, or 0 for the whole "
                "horizon"
            )
        if self.anneal.horizon_start > horizon:
            raise ValueError(
                f"anneal.horizon_start = {self.anneal.horizon_start} is longer than the task's "
                f"horizon (env.task.horizon = {horizon}); give at most {horizon}, or 0 for the "
                "whole horizon from the start"
            )
        _in_range("threads", self.threads, 0)
        if self.vmap_runs is not None:
            _in_range("vmap_runs", self.vmap_runs, 0)
        _in_range("eval_episodes", self.eval_episodes, 1)
        _in_range("checkpoints_kept", self.checkpoints_kept, 1)


# `python -m hds.discover` (conf/discover.yaml): the run's schema plus a measured dataset. Here,
# beside Config, since compose() and the command-line checks need it and hds.discover sits
# above the config layer (tests/test_layers.py).
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
    effect_type = _effects_library().effect_type
    return any(not effect_type(e.name).friction or real.friction_gap > 0 for e in real.effects)


def run_label(run: dict) -> str:
    """A run of the batch as one name, its seed and every swept setting: seed0_step_size0.04."""
    return "_".join(f"{k}{v:g}" if isinstance(v, float) else f"{k}{v}" for k, v in run.items())


def register() -> None:
    """Register the schemas with Hydra's ConfigStore (`config_schema`, `discover_schema`), which
    conf/config.yaml and conf/discover.yaml build on: done on importing hds.config."""
    ConfigStore.instance().store(name="config_schema", node=Config)
    ConfigStore.instance().store(name="discover_schema", node=DiscoverAppConfig)
