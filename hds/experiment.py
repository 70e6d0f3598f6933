"""The experiment layer: a validated config -> the batch of runs -> training with hooks ->
evaluation on the simulator and the plant -> a typed `Result`.

Everything above the jitted core calls this module (`python -m hds.run`, the loop, gap
discovery's retrain, animations, benchmarks, tests), each method through one
`train_and_evaluate`; it calls only downward (config, the simulator kinds of hds.simulators,
plants, the trainer, checkpoints, saved policies, the logger). What it opens (checkpoint
managers, progress bars, W&B runs) it closes, also when a run fails.

    result = hds.train(hds.compose(["method=pods_cl", "seeds=3"]), out_dir="outputs/mine")
    result.rows                                      # per method and run: sim/real return, gap
    policy = hds.load_policy(result.run_dir, seed=1) # u = policy(obs)  (hds/policy.py)

A directory trained again with the same config resumes from its checkpoints and ends with
exactly the numbers an uninterrupted run gives.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from hds import plots, policy_store, rundir, simulators
from hds.algo.pods import Trainer, make_train_from_config
from hds.animate import animate_episodes
from hds.checkpoint import Checkpoints
from hds.config import Config, env_config
from hds.effects.apply import applied
from hds.envs import Env, make_env
from hds.gap import Evaluator, diverged, gap_rows
from hds.logger import RunLogger, print_table
from hds.real import make_plant
from hds.real.brax_plant import BraxPlant
from hds.results import Row, Summary
from hds.simulators import Simulator, friction_gap_of
from hds.utils.io import atomic_write_json
from hds.utils.runtime import (
    RunByRun,
    enable_compilation_cache,
    over_runs,
    program_key,
    runs_vmapped,
    start_and_compile,
)

log = logging.getLogger("hds")

# the interface the commands and the API call (hds.run, hds.loop, hds.discover's retrain,
# hds.report, hds.train); the rest are this module's stages
__all__ = [
    "Hooks",
    "Result",
    "Training",
    "retrain",
    "run",
    "run_plants",
    "sim_vs_real_gif",
    "simulator_of",
    "train_batch",
    "train_and_evaluate",
]


@dataclass
class Hooks:
    """What a caller sees of training, as brax's trainers offer it.

    progress_fn(epoch, metrics): after every epoch; metrics {name: array [n_runs]} of that
        epoch (return, loss, step_size, ...) plus "method" (the rows' label).
    policy_params_fn(epoch, params): after every compiled chunk of epochs (and checkpoint);
        params: the policy parameters of every run, stacked [n_runs, ...].
    console: the progress bar and the final table; live_progress: the bar redrawn in place
        (False: a line at each tenth of the epochs, for jobs that share a terminal or a log file).
    """

    progress_fn: Callable[[int, dict], None] | None = None
    policy_params_fn: Callable[[int, object], None] | None = None
    console: bool = True
    live_progress: bool = True


@dataclass
class Training:
    """What one method's training returns: the parameters of every run [n_runs, ...], the
    metric history {name: [n_runs][epochs]}, timings, and the trainer (its policy module)."""

    method: str
    params: object
    history: dict
    timing: dict
    trainer: Trainer
    env: Env
    effects: object = None  # each run's effect parameters of env, stacked (None: env's own)


@dataclass
class Result:
    """A finished experiment: its rows (`hds.results.Row`, one per method and run of the
    batch: method, seed, swept settings, sim_return, real_return, gap, gap_relative) and
    everything summary.json records (`hds.results.Summary`)."""

    name: str
    run_dir: Path
    rows: list[Row]
    histories: dict = field(default_factory=dict)
    rows_eval_plants: list[Row] = field(default_factory=list)  # on cfg.eval_plants
    timing: dict = field(default_factory=dict)
    dynamics: dict = field(default_factory=dict)
    discovery: dict = field(default_factory=dict)
    real: dict = field(default_factory=dict)

    def to_summary(self) -> Summary:
        return Summary(
            self.name,
            self.rows,
            self.rows_eval_plants,
            self.timing,
            self.dynamics,
            self.discovery,
            self.real,
            self.histories,
        )

    def summary(self) -> dict:
        """summary.json's content (`Summary.to_json`)."""
        return self.to_summary().to_json()

    @classmethod
    def from_summary(cls, summary: Summary | dict, run_dir: Path) -> Result:
        s = summary if isinstance(summary, Summary) else Summary.from_json(summary)
        return cls(
            s.name,
            Path(run_dir),
            s.rows,
            s.history,
            s.rows_eval_plants,
            s.timing,
            s.dynamics,
            s.discovery,
            s.real,
        )


# --- the batch of runs ------------------------------------------------------------------------


def run_plants(cfg: Config) -> list:
    """The plant each run of the batch is evaluated on: one per friction gap."""
    gaps = [friction_gap_of(cfg, r) for r in cfg.runs()]
    plants = {
        g: make_plant(dataclasses.replace(cfg.real, friction_gap=g), cfg.env) for g in set(gaps)
    }
    return [plants[g] for g in gaps]


def dynamics_model(cfg: Config, env, plant, out_dir: Path):
    """The learned dynamics engine for HDS, or None when dynamics.model is none."""
    if not cfg.uses_model():
        return None, {}
    from hds.dynamics import build

    return build(cfg.dynamics, env, plant, jax.random.PRNGKey(cfg.seed), out_dir / "dynamics")


def simulator_of(cfg: Config, run_dir: Path, method: str | None = None) -> Simulator:
    """The simulator a finished run's `method` trained on (its kind's `restore`), rebuilt
    from what the run wrote (no data is measured again)."""
    return simulators.of(cfg, method).restore(cfg, Path(run_dir))


def methods_of(cfg: Config, out_dir: Path, plant):
    """(method, Simulator, model) of each policy the run trains (its simulator kind's build,
    and an oracle beside it: `oracle`), and the JSON report of the learned model."""
    env = make_env(cfg.env)
    kind = simulators.of(cfg)
    built = kind.build(cfg, env, plant, out_dir)
    # the model corrects (a residual's base) and is judged against the simulator the method
    # trains on: with simulator=corrected, the corrected one, not the raw cfg.env
    model, model_report = dynamics_model(cfg, built.env, plant, out_dir)
    methods = [(kind.label(cfg), built, model)]
    if cfg.oracle and cfg.real.plant == "brax" and kind.name != "real":
        methods.append(
            ("oracle", simulators.of(cfg, "oracle").build(cfg, env, plant, out_dir), None)
        )
    return methods, model_report


# --- training ----------------------------------------------------------------------------------


def _shard(tree):
    """Split the batch axis across devices when there are several and it divides evenly."""
    devices = jax.devices()
    n = jax.tree.leaves(tree)[0].shape[0]
    if len(devices) == 1 or n % len(devices):
        return tree
    sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
    return jax.device_put(tree, sharding)


def batch_hparams(cfg: Config, trainer: Trainer, effects=None) -> dict:
    """The trainer's numeric hyperparameters for every run of the batch, stacked: the
    defaults, each swept setting, and each run's effect parameters when given."""
    runs = cfg.runs()
    hparams = jax.tree.map(lambda x: jnp.stack([x] * len(runs)), trainer.default_hparams)
    for key, _ in cfg.sweep.items():
        if key in hparams:
            hparams[key] = jnp.asarray([r[key] for r in runs], jnp.float32)
    if effects is not None:
        hparams["effects"] = effects
    return hparams


def trainer_program_key(cfg: Config, fn) -> str | None:
    """The program cache's key of the trainer's `fn` (init, run_chunk) under `cfg`, without the
    keys that change no result (hds.rundir.IGNORED): the logger's W&B group names the sweep's
    directory, new in every `make run`, so with it no later run reused a program."""
    kept = {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg)}
    for dotted in (k for k in rundir.IGNORED if "." in k):  # a group's key: e.g. its threads
        group, name = dotted.split(".", 1)
        kept[group] = dataclasses.replace(kept[group], **{name: None})
    return program_key({k: v for k, v in kept.items() if k not in rundir.IGNORED}, fn)


def compiled_programs(cfg: Config, trainer: Trainer, hparams):
    """The batch's jitted `init(keys, hparams)` and `run_chunk(state, hparams)`, mapped over the
    runs as `cfg.vmap_runs` says, and the runs' keys (sharded where the batch is vmapped)."""
    runs = cfg.runs()
    keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray([r["seed"] for r in runs]))
    vmapped = runs_vmapped(cfg.vmap_runs, len(runs))
    if vmapped == 1:  # one run's program, whatever the batch: compiled once (RunByRun)
        key = functools.partial(trainer_program_key, cfg)
        chunk = RunByRun(trainer.run_chunk, key=key(trainer.run_chunk), threads=cfg.threads)
        init = RunByRun(trainer.init, key=key(trainer.init), threads=cfg.threads)
        return init, chunk, keys, hparams
    if vmapped == len(runs):  # a loop over the runs cannot be split across devices
        keys, hparams = _shard((keys, hparams))
    init = jax.jit(over_runs(trainer.init, vmapped, len(runs)))
    run_chunk = jax.jit(over_runs(trainer.run_chunk, vmapped, len(runs)))
    return init, run_chunk, keys, hparams


def abstract_state(cfg: Config, trainer: Trainer):
    """The shapes and dtypes of the batch's train state, with nothing computed: what a
    checkpoint is restored into."""
    hparams = batch_hparams(cfg, trainer)
    _, _, keys, hparams = compiled_programs(cfg, trainer, hparams)
    return jax.eval_shape(jax.vmap(trainer.init), keys, hparams)


def train_batch(
    cfg: Config,
    env: Env,
    out_dir: Path,
    method: str,
    model=None,
    effects=None,
    hooks: Hooks | None = None,
    logger: RunLogger | None = None,
    init_params=None,
    randomization=None,
    restore_from: Path | None = None,
) -> Training:
    """Train the batch of `cfg.runs()` together on `env` (and a learned `model`);
    `effects`: each run's effect parameters of env, stacked; `randomization`: each rollout's
    drawn (hds.algo.randomize). Resumes from out_dir/checkpoints/<method> when it has a
    checkpoint, else from `restore_from` (another run's checkpoints of the same training:
    hds.loop's loop.start_from) when given; `logger` (optional) shows progress and records to
    W&B; `init_params` (the policies of every run, stacked) warm-starts it. The returned
    policies are saved to out_dir/policies/<method> (hds.policy_store), what
    `hds.load_policy` reads."""
    hooks = hooks or Hooks()
    trainer = make_train_from_config(cfg, env, model, randomization)
    hparams = batch_hparams(cfg, trainer, effects)
    init, run_chunk, keys, hparams = compiled_programs(cfg, trainer, hparams)

    ckpt = Checkpoints(out_dir / "checkpoints" / method, keep=cfg.checkpoints_kept)
    own = ckpt.latest() is not None or restore_from is None
    source = ckpt if own else Checkpoints(restore_from)
    try:
        state, compiled, timing = _state_and_program(
            cfg, trainer, source, init, run_chunk, keys, hparams, init_params
        )
        history: dict[str, list] = {}
        if source.latest() is not None:
            state, meta = source.restore(state, resuming=own)
            history = {k: [list(map(float, row)) for row in v] for k, v in meta["history"].items()}
            where = "" if own else f" of {restore_from}"
            log.info("resuming %s from epoch %d%s", method, int(state.epoch[0]), where)
        if logger:
            logger.start(int(state.epoch[0]))
        start, cpu_start = time.perf_counter(), time.process_time()
        while int(state.epoch[0]) < cfg.algo.epochs:
            if compiled is None:  # the trained checkpoint was unreadable: an earlier one
                compiled = run_chunk.lower(state, hparams).compile()
            t0 = time.perf_counter()
            epoch0 = int(state.epoch[0])
            state, metrics = compiled(state, hparams)
            metrics = {k: np.asarray(v, dtype=float) for k, v in metrics.items()}
            for k, v in metrics.items():
                rows = history.setdefault(k, [[] for _ in range(v.shape[0])])
                for s in range(v.shape[0]):
                    rows[s].extend(map(float, v[s]))
            ckpt.save(int(state.epoch[0]), state, {"history": history, "method": method})
            seconds = (time.perf_counter() - t0) / trainer.chunk
            _report_chunk(hooks, logger, method, epoch0, metrics, seconds)
            _check_finite(state, method)
            if hooks.policy_params_fn:
                hooks.policy_params_fn(int(state.epoch[0]), state.policy)
        timing["train_s"] = time.perf_counter() - start
        # CPU seconds of the whole process (all its threads): on a shared machine the wall
        # clock measures the neighbours too
        timing["train_cpu_s"] = time.process_time() - cpu_start
    finally:
        ckpt.close()
        if not own:
            source.close()
    params = trainer.final_policy(state)
    policy_store.save(
        out_dir / "policies" / method, trainer.policy, params, cfg.runs(), state.epoch
    )
    return Training(method, params, history, timing, trainer, env, effects)


def _state_and_program(cfg, trainer, source, init, run_chunk, keys, hparams, init_params):
    """(state, compiled chunk, timing) to train from: the runs' initial state (warm-started
    with `init_params`) and the chunk compiled for it; where `source` already holds the
    trained epochs, the state's shapes to restore into and no program (nothing to train)."""
    start = time.perf_counter()
    prepare = None if init_params is None else (lambda s: s.replace(policy=init_params))
    if (source.latest() or 0) >= cfg.algo.epochs:  # trained: restored into its shapes only
        state, compiled = jax.eval_shape(jax.vmap(trainer.init), keys, hparams), None
    elif isinstance(init, RunByRun):  # init compiled and run while the chunk compiles
        state, compiled = start_and_compile(init, run_chunk, keys, hparams, prepare)
    else:
        state = init(keys, hparams)
        state = prepare(state) if prepare else state
        compiled = run_chunk.lower(state, hparams).compile()
    timing = {"compile_s": time.perf_counter() - start}
    return state, compiled, timing


def _report_chunk(hooks: Hooks, logger, method: str, epoch0: int, metrics: dict, seconds: float):
    if logger:
        logger.log_epochs(epoch0, metrics, seconds)
    if hooks.progress_fn:
        for i in range(next(iter(metrics.values())).shape[1]):
            hooks.progress_fn(
                epoch0 + i + 1, {"method": method, **{k: v[:, i] for k, v in metrics.items()}}
            )


def _check_finite(state, method: str) -> None:
    # numpy: jnp's eager isfinite and all compiled two small programs per parameter's shape
    if not all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(state.policy)):
        raise FloatingPointError(
            f"{method}: the policy parameters are no longer finite; lower algo.learning_rate or "
            "algo.step_size, or check the simulator for NaN states (env.backend, env.timestep)"
        )


# --- evaluation --------------------------------------------------------------------------------


def evaluate_training(cfg: Config, training: Training, plants) -> tuple[list[Row], list[Row]]:
    """One row per run: mean return on the simulator the policy trained on (what it was
    promised) and on its plant, from the same initial states; and the same on each plant of
    `cfg.eval_plants`. Each row names its plant. Runs whose rollouts diverged are named in a
    warning."""
    evaluator = Evaluator(
        training.env, training.trainer.policy, plants, cfg.eval_episodes, cfg.eval_seed
    )
    sim = evaluator.sim_returns(training.params, training.effects)

    def rows_on(plant, label: dict) -> list[Row]:
        runs = [{**label, **r} for r in cfg.runs()]
        real = evaluator.real_returns(training.params, plant)
        for line in diverged(training.method, runs, sim, real, training.history.get("return")):
            log.warning(line)
        return gap_rows(training.method, runs, sim, real, cfg.env.task.solved_at)

    own = rows_on(plants, {"plant": cfg.real.label()})
    others = [
        row
        for real, plant in eval_plants(cfg)
        for row in rows_on(plant, {"plant": real.label(), "friction_gap": real.friction_gap})
    ]
    return own, others


def eval_plants(cfg: Config) -> list[tuple]:
    """(config, plant) of each further plant the policies are evaluated on, at its own
    friction gap (a swept gap applies to the run's own plant only)."""
    return [(real, make_plant(real, cfg.env)) for real in cfg.eval_plants.values()]


# --- the whole experiment ------------------------------------------------------------------------


def train_and_evaluate(
    cfg: Config,
    method: str,
    simulator: Simulator,
    out_dir: Path,
    plants,
    hooks: Hooks | None = None,
    model=None,
    init_params=None,
    figures: bool = False,
    before_close: Callable | None = None,
    restore_from: Path | None = None,
) -> tuple[Training, list[dict], list[dict]]:
    """One method: its progress bar and W&B run opened, trained on `simulator` (and a learned
    `model`; warm-started from `init_params`; resumed from another run's checkpoints
    `restore_from`, train_batch), evaluated on `plants` (each run's) and on
    cfg.eval_plants, the rows logged (with the learning curves and sim-vs-real figures when
    `figures`), `before_close(logger, training)` called, the logger closed however it ends.
    Returns (training, rows on the runs' plants, rows on eval_plants). `hds.train`, the
    loop's rounds and the discovery's retrain all train through this."""
    hooks = hooks or Hooks()
    with method_logger(cfg, out_dir, method, hooks) as logger:
        training = train_batch(
            cfg,
            simulator.env,
            out_dir,
            method,
            model,
            simulator.effects,
            hooks,
            logger,
            init_params=init_params,
            randomization=simulator.randomization,
            restore_from=restore_from,
        )
        rows, rows_eval_plants = evaluate_training(cfg, training, plants)
        logger.finish(rows, _method_figures(method, training.history, rows) if figures else {})
        if before_close:
            before_close(logger, training)
    return training, rows, rows_eval_plants


def run(cfg: Config, out_dir: str | Path | None = None, hooks: Hooks | None = None) -> Result:
    """Train and evaluate every method of the run (`hds.train`); write out_dir/summary.json,
    checkpoints/, policies/, plots/ and W&B logs (default out_dir: outputs/runs/<name>/<time>).
    A directory that already has its summary.json is a finished job (of a sweep started again):
    its result is read back, nothing is trained."""
    hooks = hooks or Hooks()
    enable_compilation_cache()
    out_dir = Path(out_dir or Path("outputs/runs") / cfg.name / time.strftime("%Y-%m-%d_%H-%M-%S"))
    if (out_dir / "summary.json").is_file():
        log.info("%s is finished (summary.json exists): skipped", out_dir)
        return Result.from_summary(Summary.read(out_dir / "summary.json"), out_dir)
    plants = run_plants(cfg)
    if cfg.real.family:  # a lab plant: its draw's truth beside the results (hds.real.lab)
        from hds.real.lab import draw

        atomic_write_json(out_dir / "truth.json", draw(cfg.real.family, cfg.real.draw))
    # all alike unless the gap is swept, which excludes a learned model and a corrected simulator
    methods, model_report = methods_of(cfg, out_dir, plants[0])
    discovery = methods[0][1].report
    result = Result(
        cfg.name,
        out_dir,
        [],
        dynamics=model_report,
        discovery=discovery,
        real={
            "plant": cfg.real.plant,
            "name": cfg.real.label(),
            "friction_gap": cfg.real.friction_gap,
            # what the plant applies (friction scaled): the truth discovery is judged against
            "effects": applied(cfg.real.effects, cfg.real.friction_gap),
        },
    )
    for method, simulator, model in methods:

        def extras(logger, training, method=method):
            if discovery and method == methods[0][0]:
                logger.log_discovery("discovery_report", out_dir / "discovery")
            if cfg.gif:
                gif = sim_vs_real_gif(cfg, training, plants[0], out_dir / "plots")
                logger.log_files({"sim_vs_real_gif": gif})

        training, rows, rows_eval_plants = train_and_evaluate(
            cfg, method, simulator, out_dir, plants, hooks, model, figures=True, before_close=extras
        )
        result.rows += rows
        result.rows_eval_plants += rows_eval_plants
        result.histories[method], result.timing[method] = training.history, training.timing
    if hooks.console:
        print_table(
            result.rows + result.rows_eval_plants,
            title=f"{cfg.name}: return on the simulator and on the {cfg.real.plant} plant",
        )
    keys = plots.varying_keys(result.rows)
    figures = {
        "learning_curves": plots.learning_curves(
            {
                plots.label(row, keys): h
                for row, h in plots.histories_by_setting(result.rows, result.histories, keys)
            }
        ),
        "sim_vs_real": plots.sim_vs_real(result.rows),
    }
    for name, fig in figures.items():
        plots.save(fig, out_dir / "plots" / f"{name}.png")
    result.to_summary().write(out_dir / "summary.json")
    return result


def retrain(cfg: Config, corrected_env: dict, out_dir: Path) -> dict:
    """`python -m hds.discover retrain=true`: the policy's sim2real gap before and after the
    correction. PODS is trained on the original simulator and on the corrected one (the same
    config, seeds and budget), and each policy is evaluated on its own simulator and on the
    plant of `real` (the plant that produced the data) from the same initial states."""
    plant = make_plant(cfg.real, cfg.env)
    rows = []
    for method, env_cfg in (("original", cfg.env), ("corrected", env_config(corrected_env))):
        log.info("retrain: PODS on the %s simulator", method)
        simulator = Simulator(make_env(env_cfg))
        _, method_rows, _ = train_and_evaluate(cfg, method, simulator, Path(out_dir), plant)
        rows += method_rows
    plant_desc = {
        "plant": cfg.real.plant,
        "friction_gap": cfg.real.friction_gap,
        "effects": applied(cfg.real.effects, cfg.real.friction_gap),  # the force it applied
    }
    return {"plant": plant_desc, "rows": [r.to_json() for r in rows]}  # JSON-ready: report.json


def sim_vs_real_gif(cfg: Config, training: Training, plant, out_dir: Path) -> Path:
    """The batch's first policy, one evaluation episode on the simulator it trained on beside
    the same on `plant`, drawn into out_dir/<method>_sim_vs_real.gif (`gif=true`)."""
    env = training.env
    params = jax.tree.map(lambda x: x[0], training.params)
    evaluator = Evaluator(env, training.trainer.policy, plant, episodes=1, seed=cfg.eval_seed)
    sim, real = (evaluator.episodes(params, p) for p in (BraxPlant(env), plant))
    path = out_dir / f"{training.method}_sim_vs_real.gif"
    names, dt = env.sim.obs_names, env.sim.dt
    return animate_episodes(sim, real, names, cfg.real.plant, dt, path, cfg.env.xml)


def _method_figures(method: str, history: dict, rows: list[Row]) -> dict:
    return {
        "learning_curves": plots.learning_curves({method: history}),
        "sim_vs_real": plots.sim_vs_real(rows),
    }


@contextlib.contextmanager
def method_logger(cfg: Config, out_dir: Path, method: str, hooks: Hooks):
    """The progress bar and W&B run of one method, closed however training ends."""
    logger = RunLogger(
        cfg, out_dir, method, cfg.runs(), console=hooks.console, live=hooks.live_progress
    )
    try:
        yield logger
    except BaseException:
        logger.close(failed=True)
        raise
    logger.close()
