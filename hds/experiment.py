"""The experiment layer: a validated config -> the batch of runs -> training with hooks ->
evaluation on the simulator and the plant -> a typed `Result`.

Everything above the jitted core calls this module (`python -m hds.run`, gap discovery's
retrain, `hds.load_policy`, animations, benchmarks, tests); it calls only downward (config,
envs, plants, the trainer, checkpoints, the logger). What it opens (checkpoint managers,
progress bars, W&B runs) it closes, also when a run fails.

    result = hds.train(hds.compose(["method=pods_cl", "seeds=3"]), out_dir="outputs/mine")
    result.rows                                      # per method and run: sim/real return, gap
    policy = hds.load_policy(result.run_dir, seed=1) # u = policy(obs)  (hds/policy.py)

A directory trained again with the same config resumes from its checkpoints and ends with
exactly the numbers an uninterrupted run gives.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from hds import plots
from hds.algo.pods import Trainer, make_train_from_config
from hds.algo.randomize import randomized_env
from hds.animate import animate_episodes
from hds.checkpoint import Checkpoints
from hds.config import Config, env_config
from hds.data import concatenate, save
from hds.effects.apply import applied, place
from hds.envs import Env, make_env
from hds.evaluation import Evaluator, diverged, gap_rows
from hds.logger import RunLogger, print_table
from hds.real import make_plant
from hds.real.brax_plant import BraxPlant
from hds.utils.io import atomic_write_json, read_json
from hds.utils.runtime import enable_compilation_cache, over_runs, runs_vmapped

log = logging.getLogger("hds")


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
    """A finished experiment: its rows (one per method and run of the batch: method, seed,
    swept settings, sim_return, real_return, gap, gap_relative) and everything summary.json
    records."""

    name: str
    run_dir: Path
    rows: list[dict]
    histories: dict = field(default_factory=dict)
    rows_eval_plants: list[dict] = field(default_factory=list)  # on cfg.eval_plants
    timing: dict = field(default_factory=dict)
    dynamics: dict = field(default_factory=dict)
    discovery: dict = field(default_factory=dict)
    real: dict = field(default_factory=dict)

    def summary(self) -> dict:
        return {
            "name": self.name,
            "rows": self.rows,
            "rows_eval_plants": self.rows_eval_plants,
            "timing": self.timing,
            "dynamics": self.dynamics,
            "discovery": self.discovery,
            "real": self.real,
            "history": self.histories,
        }

    @classmethod
    def from_summary(cls, summary: dict, run_dir: Path) -> Result:
        return cls(
            summary["name"],
            Path(run_dir),
            summary["rows"],
            summary.get("history", {}),
            summary.get("rows_eval_plants", []),
            summary.get("timing", {}),
            summary.get("dynamics", {}),
            summary.get("discovery", {}),
            summary.get("real", {}),
        )


# --- the batch of runs ------------------------------------------------------------------------


def method_name(cfg: Config) -> str:
    """The label of the run's rows: its algorithm, learned model and simulator (pods, hds+mlp,
    pods+corrected, oracle)."""
    if cfg.simulator == "real":
        return "oracle" if cfg.algo.name == "pods_cl" else f"{cfg.algo.name}+oracle"
    parts = [cfg.algo.name]
    if cfg.uses_model():
        parts.append(cfg.dynamics.model)
    if cfg.simulator == "corrected":
        parts.append("corrected")
    if cfg.simulator == "randomized":
        parts.append("dr")
    return "+".join(parts)


def friction_gap_of(cfg: Config, run: dict) -> float:
    return run.get("friction_gap", cfg.real.friction_gap)


# --- what each method trains on -----------------------------------------------------------------


def real_dynamics(cfg: Config):
    """The simulator with the plant's own effects (friction smoothed so it differentiates),
    and each run's effect parameters (its friction gap), stacked."""
    env = make_env(cfg.env, effects=list(cfg.real.effects), friction_gap=cfg.real.friction_gap)
    per_run = [
        place(list(cfg.real.effects), env.sim.targets, friction_gap_of(cfg, r))[1]
        for r in cfg.runs()
    ]
    return env, jax.tree.map(lambda *x: jnp.stack(x), *per_run)


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


def corrected_simulator(cfg: Config, env, plant, out_dir: Path):
    """The simulator plus the effects gap discovery names on data measured on the plant (the
    data a learned model of this seed is fitted on, and, while they cannot identify what more
    excitation would, more of it at doubled amplitude: hds.discover.record_until_identifiable);
    the data and the report go to out_dir/discovery. Returns (env, JSON-ready summary of the
    findings)."""
    from hds.discover import corrected_env, discover, record_until_identifiable, write_report
    from hds.dynamics import collect_data, measured_data

    key = jax.random.split(jax.random.PRNGKey(cfg.seed))[0]
    data, source = measured_data(cfg.dynamics, env, plant, key)
    if source["data"] == "plant":

        def record(scale, attempt):  # the first: the learned model's data
            if not attempt:
                return data
            dyn = dataclasses.replace(cfg.dynamics, excitation_scale=scale)
            return collect_data(dyn, env, plant, jax.random.fold_in(key, attempt))

        recorded, scale, notes = record_until_identifiable(
            record, cfg.env, cfg.discover, cfg.dynamics.excitation_scale
        )
        data = concatenate(recorded)
        source |= {"episodes": data.n_episodes, "excitation_scale": scale, "notes": notes}
        for note in notes:
            log.info("active excitation: %s", note)
        save(data, out_dir / "discovery" / "data.npz")  # what discovery read, to re-run it on
    result = discover(data, cfg.env, cfg.discover)
    write_report(
        result, cfg.env, out_dir / "discovery", cfg.discover.plot_episodes, cfg.discover.bins
    )
    found = [e.to_json() for e in result.missing_effects]
    log.info(
        "gap discovery named: %s",
        ", ".join(f"{e['name']}@{e['target']} {e['params']}" for e in found) or "nothing",
    )
    for warning in result.warnings:
        log.warning("gap discovery: %s", warning)
    summary = {**source, "effects": found, "warnings": result.warnings}
    return make_env(env_config(corrected_env(cfg.env, result))), summary


def simulator_of(cfg: Config, run_dir: Path, method: str | None = None) -> tuple[Env, object]:
    """The simulator a finished run's `method` trained on, and its runs' effect parameters
    (None: the env's own), rebuilt from what the run wrote (no data is measured again)."""
    method = method or method_name(cfg)
    if cfg.simulator == "real" or method == "oracle":
        return real_dynamics(cfg)
    if cfg.simulator == "corrected":
        return make_env(corrected_env_config(run_dir)), None
    if cfg.simulator == "randomized":
        return randomized_env(cfg), None
    return make_env(cfg.env), None


def corrected_env_config(run_dir: Path):
    """The env config gap discovery wrote into a finished corrected-simulator run."""
    from omegaconf import OmegaConf

    found = sorted((Path(run_dir) / "discovery" / "conf" / "env").glob("*.yaml"))
    if not found:
        raise FileNotFoundError(
            f"{run_dir}/discovery/conf/env/ holds no corrected env config: the run did not "
            "finish its gap discovery; train it again on the same directory"
        )
    return env_config(OmegaConf.to_container(OmegaConf.load(found[0])))


def methods_of(cfg: Config, out_dir: Path, plant):
    """(method, env, effects, model) of each policy the run trains, and the JSON reports of the
    learned model and of gap discovery."""
    env = make_env(cfg.env)
    model, model_report = dynamics_model(cfg, env, plant, out_dir)
    train_env, effects, discovery = env, None, {}
    if cfg.simulator == "real":
        train_env, effects = real_dynamics(cfg)
    elif cfg.simulator == "corrected":
        train_env, discovery = corrected_simulator(cfg, env, plant, out_dir)
    elif cfg.simulator == "randomized":
        train_env = randomized_env(cfg)
    methods = [(method_name(cfg), train_env, effects, model)]
    if cfg.oracle and cfg.real.plant == "brax" and cfg.simulator != "real":
        methods.append(("oracle", *real_dynamics(cfg), None))
    return methods, model_report, discovery


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


def compiled_programs(cfg: Config, trainer: Trainer, hparams):
    """The batch's jitted `init(keys, hparams)` and `run_chunk(state, hparams)`, mapped over the
    runs as `cfg.vmap_runs` says, and the runs' keys (sharded where the batch is vmapped)."""
    runs = cfg.runs()
    keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray([r["seed"] for r in runs]))
    vmapped = runs_vmapped(cfg.vmap_runs, len(runs))
    if vmapped == len(runs):  # a loop over the runs cannot be split across devices
        keys, hparams = _shard((keys, hparams))
    init = jax.jit(over_runs(trainer.init, vmapped, len(runs)))
    run_chunk = jax.jit(over_runs(trainer.run_chunk, vmapped, len(runs)))
    return init, run_chunk, keys, hparams


def abstract_state(cfg: Config, trainer: Trainer):
    """The shapes and dtypes of the batch's train state, with nothing computed: what a
    checkpoint is restored into."""
    hparams = batch_hparams(cfg, trainer)
    init, _, keys, hparams = compiled_programs(cfg, trainer, hparams)
    return jax.eval_shape(init, keys, hparams)


def train(
    cfg: Config,
    env: Env,
    out_dir: Path,
    method: str,
    model=None,
    effects=None,
    hooks: Hooks | None = None,
    logger: RunLogger | None = None,
    init_params=None,
) -> Training:
    """Train the batch of `cfg.runs()` together on `env` (and a learned `model`);
    `effects`: each run's effect parameters of env, stacked. Resumes from
    out_dir/checkpoints/<method> when it has a checkpoint; `logger` (optional) shows progress
    and records to W&B; `init_params` (the policies of every run, stacked) warm-starts it."""
    hooks = hooks or Hooks()
    trainer = make_train_from_config(cfg, env, model)
    hparams = batch_hparams(cfg, trainer, effects)
    init, run_chunk, keys, hparams = compiled_programs(cfg, trainer, hparams)

    start = time.perf_counter()
    state = init(keys, hparams)
    if init_params is not None:
        state = state.replace(policy=init_params)
    compiled = run_chunk.lower(state, hparams).compile()
    timing = {"compile_s": time.perf_counter() - start}

    ckpt = Checkpoints(out_dir / "checkpoints" / method, keep=cfg.checkpoints_kept)
    try:
        history: dict[str, list] = {}
        if ckpt.latest() is not None:
            state, meta = ckpt.restore(state, resuming=True)
            history = {k: [list(map(float, row)) for row in v] for k, v in meta["history"].items()}
            log.info("resuming %s from epoch %d", method, int(state.epoch[0]))
        if logger:
            logger.start(int(state.epoch[0]))
        start, cpu_start = time.perf_counter(), time.process_time()
        while int(state.epoch[0]) < cfg.algo.epochs:
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
    return Training(method, trainer.final_policy(state), history, timing, trainer, env, effects)


def _report_chunk(hooks: Hooks, logger, method: str, epoch0: int, metrics: dict, seconds: float):
    if logger:
        logger.log_epochs(epoch0, metrics, seconds)
    if hooks.progress_fn:
        for i in range(next(iter(metrics.values())).shape[1]):
            hooks.progress_fn(
                epoch0 + i + 1, {"method": method, **{k: v[:, i] for k, v in metrics.items()}}
            )


def _check_finite(state, method: str) -> None:
    if not all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(state.policy)):
        raise FloatingPointError(
            f"{method}: the policy parameters are no longer finite; lower algo.learning_rate or "
            "algo.step_size, or check the simulator for NaN states (env.backend, env.timestep)"
        )


# --- evaluation --------------------------------------------------------------------------------


def evaluate_training(cfg: Config, training: Training, plants) -> tuple[list, list]:
    """One row per run: mean return on the simulator the policy trained on (what it was
    promised) and on its plant, from the same initial states; and the same on each plant of
    `cfg.eval_plants`. Each row names its plant. Runs whose rollouts diverged are named in a
    warning."""
    evaluator = Evaluator(
        training.env, training.trainer.policy, plants, cfg.eval_episodes, cfg.eval_seed
    )
    sim = evaluator.sim_returns(training.params, training.effects)

    def rows_on(plant, label: dict) -> list[dict]:
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


def run(cfg: Config, out_dir: str | Path | None = None, hooks: Hooks | None = None) -> Result:
    """Train and evaluate every method of the run (`hds.train`); write out_dir/summary.json,
    checkpoints/, plots/ and W&B logs (default out_dir: outputs/runs/<name>/<time>). A
    directory that already has its summary.json is a finished job (of a sweep started again):
    its result is read back, nothing is trained."""
    hooks = hooks or Hooks()
    enable_compilation_cache()
    out_dir = Path(out_dir or Path("outputs/runs") / cfg.name / time.strftime("%Y-%m-%d_%H-%M-%S"))
    if (out_dir / "summary.json").is_file():
        log.info("%s is finished (summary.json exists): skipped", out_dir)
        return Result.from_summary(read_json(out_dir / "summary.json"), out_dir)
    plants = run_plants(cfg)
    # all alike unless the gap is swept, which excludes a learned model and a corrected simulator
    methods, model_report, discovery = methods_of(cfg, out_dir, plants[0])
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
    for method, method_env, method_effects, method_model in methods:
        with method_logger(cfg, out_dir, method, hooks) as logger:
            training = train(
                cfg, method_env, out_dir, method, method_model, method_effects, hooks, logger
            )
            rows, rows_eval_plants = evaluate_training(cfg, training, plants)
            logger.finish(rows, _method_figures(method, training.history, rows))
            if discovery and method == methods[0][0]:
                logger.log_discovery("discovery_report", out_dir / "discovery")
            if cfg.gif:
                gif = sim_vs_real_gif(cfg, training, plants[0], out_dir / "plots")
                logger.log_files({"sim_vs_real_gif": gif})
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
    atomic_write_json(out_dir / "summary.json", result.summary())
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
        with method_logger(cfg, Path(out_dir), method, Hooks()) as logger:
            training = train(cfg, make_env(env_cfg), Path(out_dir), method, logger=logger)
            method_rows, _ = evaluate_training(cfg, training, plant)
            logger.finish(method_rows, {})
        rows += method_rows
    plant_desc = {
        "plant": cfg.real.plant,
        "friction_gap": cfg.real.friction_gap,
        "effects": applied(cfg.real.effects, cfg.real.friction_gap),  # the force it applied
    }
    return {"plant": plant_desc, "rows": rows}


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


def _method_figures(method: str, history: dict, rows: list[dict]) -> dict:
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
