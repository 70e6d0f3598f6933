"""`python -m hds.run`: train a policy with PODS or HDS, measure its sim2real gap, record it all.

config -> env, plant, (learned model) -> trainer compiled once for every seed -> chunks of
epochs, with a progress bar, a checkpoint and a W&B log between chunks -> evaluation on the
simulator and on the plant -> summary.json, plots/, final table.

A run started again on the same directory (`hydra.run.dir=...`) resumes from its checkpoints
and ends with exactly the numbers an uninterrupted run gives.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import os
import time
import traceback
from pathlib import Path

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")

import hydra  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from hydra.types import RunMode  # noqa: E402
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from hds import plots  # noqa: E402
from hds.algo.pods import make_train  # noqa: E402
from hds.algo.randomize import randomized_env  # noqa: E402
from hds.checkpoint import Checkpoints  # noqa: E402
from hds.config import Config, validate  # noqa: E402
from hds.effects.apply import place  # noqa: E402
from hds.envs import make_env  # noqa: E402
from hds.evaluate import Evaluator, gap_rows  # noqa: E402
from hds.logger import RunLogger, print_table  # noqa: E402
from hds.real import make_plant  # noqa: E402
from hds.utils.io import atomic_write_bytes, atomic_write_json, read_json  # noqa: E402
from hds.utils.runtime import enable_compilation_cache, over_runs, runs_vmapped  # noqa: E402

log = logging.getLogger("hds")


def wandb_group(hydra_cfg) -> str:
    """The W&B group of a run: its directory's last three parts (`multiruns/<name>/<time>` or
    `runs/<name>/<time>` by default). Every job of a multirun gets its sweep directory's, also
    when the sweep is started again on it; a single run gets its own. `logger.group=...`
    overrides it."""
    multirun = hydra_cfg.mode == RunMode.MULTIRUN
    directory = Path(str(hydra_cfg.sweep.dir if multirun else hydra_cfg.runtime.output_dir))
    return "/".join(directory.resolve().parts[-3:])[-128:]  # W&B allows 128 characters


def batch_of(cfg: Config) -> list[dict]:
    """The runs trained together: every seed crossed with every setting of `cfg.sweep`."""
    names, values = zip(*cfg.sweep.items()) if cfg.sweep.items() else ((), ())
    settings = [dict(zip(names, combo)) for combo in itertools.product(*values)]
    return [{"seed": cfg.seed + i, **setting} for setting in settings for i in range(cfg.seeds)]


def _shard(tree):
    """Split the batch axis across devices when there are several and it divides evenly."""
    devices = jax.devices()
    n = jax.tree.leaves(tree)[0].shape[0]
    if len(devices) == 1 or n % len(devices):
        return tree
    sharding = NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))
    return jax.device_put(tree, sharding)


def train(cfg: Config, env, out_dir: Path, method: str, model=None, effects=None):
    """Train the batch of `batch_of(cfg)` together; `effects` (optional): each run's effect
    parameters of `env`, stacked. Returns (policy params [batch, ...], history, timing, logger,
    trainer). Resumes from out_dir/checkpoints/<method> when it has a checkpoint."""
    trainer = make_train(cfg, env, model)
    runs = batch_of(cfg)
    hparams = jax.tree.map(lambda x: jnp.stack([x] * len(runs)), trainer.default_hparams)
    for key, _ in cfg.sweep.items():
        if key in hparams:
            hparams[key] = jnp.asarray([r[key] for r in runs], jnp.float32)
    if effects is not None:
        hparams["effects"] = effects
    keys = jax.vmap(jax.random.PRNGKey)(jnp.asarray([r["seed"] for r in runs]))
    vmapped = runs_vmapped(cfg.vmap_runs, len(runs))
    if vmapped == len(runs):  # a loop over the runs cannot be split across devices
        keys, hparams = _shard((keys, hparams))
    init = jax.jit(over_runs(trainer.init, vmapped, len(runs)))
    run_chunk = jax.jit(over_runs(trainer.run_chunk, vmapped, len(runs)))

    start = time.perf_counter()
    state = init(keys, hparams)
    compiled = run_chunk.lower(state, hparams).compile()
    timing = {"compile_s": time.perf_counter() - start}

    ckpt = Checkpoints(out_dir / "checkpoints" / method, keep=cfg.checkpoints_kept)
    history: dict[str, list] = {}
    if ckpt.latest() is not None:
        state, meta = ckpt.restore(state)
        history = {k: [list(map(float, row)) for row in v] for k, v in meta["history"].items()}
        log.info("resuming %s from epoch %d", method, int(state.epoch[0]))
    first = int(state.epoch[0])
    logger = (
        RunLogger(cfg, out_dir, method, cfg.algo.epochs, first) if first < cfg.algo.epochs else None
    )
    start = time.perf_counter()
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
        logger.log_epochs(epoch0, metrics, (time.perf_counter() - t0) / trainer.chunk)
        _check_finite(state, method)
    timing["train_s"] = time.perf_counter() - start
    ckpt.close()
    return state.policy, history, timing, logger, trainer


def _check_finite(state, method: str) -> None:
    if not all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree.leaves(state.policy)):
        raise FloatingPointError(
            f"{method}: the policy parameters are no longer finite; lower algo.learning_rate or "
            "algo.step_size, or check the simulator for NaN states (env.backend, env.timestep)"
        )


def dynamics_model(cfg: Config, env, plant, out_dir: Path):
    """The learned dynamics engine for HDS, or None when dynamics.model is none."""
    if not cfg.uses_model():
        return None, {}
    from hds.dynamics import build

    return build(cfg.dynamics, env, plant, jax.random.PRNGKey(cfg.seed), out_dir / "dynamics")


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


def real_dynamics(cfg: Config):
    """The simulator with the plant's own effects (friction smoothed so it differentiates),
    and each run's effect parameters (its friction gap), stacked."""
    env = make_env(cfg.env, effects=list(cfg.real.effects), friction_gap=cfg.real.friction_gap)
    per_run = [
        place(list(cfg.real.effects), env.sim.targets, friction_gap_of(cfg, r))[1]
        for r in batch_of(cfg)
    ]
    return env, jax.tree.map(lambda *x: jnp.stack(x), *per_run)


def run_plants(cfg: Config) -> list:
    """The plant each run of the batch is evaluated on: one per friction gap."""
    gaps = [friction_gap_of(cfg, r) for r in batch_of(cfg)]
    plants = {
        g: make_plant(dataclasses.replace(cfg.real, friction_gap=g), cfg.env) for g in set(gaps)
    }
    return [plants[g] for g in gaps]


def corrected_simulator(cfg: Config, env, plant, out_dir: Path):
    """The simulator plus the effects gap discovery names on data measured on the plant (the
    same data a learned model of this seed is fitted on); its report goes to out_dir/discovery.
    Returns (env, JSON-ready summary of the findings)."""
    from hds.discover import corrected_env, discover, write_report
    from hds.discover.retrain import env_config
    from hds.dynamics import measured_data

    data, source = measured_data(
        cfg.dynamics, env, plant, jax.random.split(jax.random.PRNGKey(cfg.seed))[0]
    )
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


def run(cfg: Config, out_dir: Path) -> dict:
    """The whole run; returns the summary also written to out_dir/summary.json. A directory
    that already has its summary.json is a finished job (of a sweep started again): skipped."""
    out_dir = Path(out_dir)
    if (out_dir / "summary.json").is_file():
        log.info("%s is finished (summary.json exists): skipped", out_dir)
        return read_json(out_dir / "summary.json")
    env = make_env(cfg.env)
    plants = run_plants(cfg)
    plant = plants[0]  # all alike unless the gap is swept, which excludes the two uses below
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

    rows, histories, timings = [], {}, {}
    for method, method_env, method_effects, method_model in methods:
        params, history, timing, logger, trainer = train(
            cfg, method_env, out_dir, method, method_model, method_effects
        )
        # sim return: on the simulator the policy trained on (what it was promised)
        evaluator = Evaluator(method_env, trainer.policy, plants, cfg.eval_episodes, cfg.eval_seed)
        method_rows = gap_rows(
            method,
            batch_of(cfg),
            evaluator.sim_returns(params, method_effects),
            evaluator.real_returns(params),
        )
        rows += method_rows
        histories[method], timings[method] = history, timing
        if logger:
            logger.finish(
                method_rows, {"learning_curves": plots.learning_curves({method: history})}
            )

    print_table(
        rows, title=f"{cfg.name}: return on the simulator and on the {cfg.real.plant} plant"
    )
    figures = {
        "learning_curves": plots.learning_curves(histories),
        "sim_vs_real": plots.sim_vs_real(rows),
    }
    for name, fig in figures.items():
        plots.save(fig, out_dir / "plots" / f"{name}.png")
    summary = {
        "name": cfg.name,
        "rows": rows,
        "timing": timings,
        "dynamics": model_report,
        "discovery": discovery,
        "real": {"plant": cfg.real.plant, "friction_gap": cfg.real.friction_gap},
        "history": histories,
    }
    atomic_write_json(out_dir / "summary.json", summary)
    return summary


@hydra.main(config_path="../conf", config_name="config", version_base="1.3")
def main(dcfg) -> float:
    hydra_cfg = HydraConfig.get()
    if dcfg.logger.group is None:
        dcfg.logger.group = wandb_group(hydra_cfg)
    out_dir = Path(hydra_cfg.runtime.output_dir)
    OmegaConf.save(dcfg, out_dir / "config.yaml", resolve=True)
    try:
        cfg = validate(dcfg)  # every range check, before anything compiles
        enable_compilation_cache()
        summary = run(cfg, out_dir)
    except Exception:
        if hydra_cfg.mode != RunMode.MULTIRUN:
            raise
        # One failed job must not stop the sweep: record why, let the others run. Starting
        # the sweep again reruns this job and skips the finished ones.
        atomic_write_bytes(out_dir / "failed.txt", traceback.format_exc().encode())
        log.exception("job %s failed; see %s", hydra_cfg.job.num, out_dir / "failed.txt")
        return float("nan")
    (out_dir / "failed.txt").unlink(missing_ok=True)
    log.info("wrote %s", out_dir / "summary.json")
    return float(np.mean([r["real_return"] for r in summary["rows"]]))


if __name__ == "__main__":
    main()
