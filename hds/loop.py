"""`python -m hds.loop`: the iterative real2sim2real loop.

  round 0   train on the simulator (cfg.env), evaluate on the plant;
  round r   deploy the current policy on the plant (`loop.deploy_episodes`) and excite it
            open loop (`loop.excitation_episodes`, stronger while the data cannot identify
            what they could: active excitation, hds.discover.identifiability); gap
            discovery on all data so far; a learned model (HDS) refitted on it; train
            warm-started on the corrected simulator (`loop.epochs`); evaluate on the plant.
Each round reports the named effects with intervals, the real return (mean and 95% interval over
the runs), the sim2real gap and the data used (episodes, and the plant time they cost: seconds
of deployment and of excitation, hds.results.PlantTime), in <out>/rounds/<r>/round.json and a
final table; the loop stops when the real return no longer rises beyond the rounds' intervals
(`improved`) and no policy that solves its simulator fails on the plant (`plant_failures`),
and leaves the policies of its latest round that no other round beats beyond the intervals
(`result_round`). Every round is checkpointed: a killed loop started again on its directory
resumes and ends with the numbers of an uninterrupted one.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")

from hds.utils.runtime import enable_compilation_cache, headless_mujoco  # noqa: E402

headless_mujoco()  # before hds's modules import MuJoCo

import hydra  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from hds import experiment, plots, rundir  # noqa: E402
from hds.commands import before_hydra  # noqa: E402
from hds.config import Config, env_config, load_config, validate  # noqa: E402
from hds.data.acquire import deployed_and_excited  # noqa: E402
from hds.data.budget import check_planned  # noqa: E402
from hds.data.format import Dataset, concatenate, load, save  # noqa: E402
from hds.envs import make_env  # noqa: E402
from hds.gap import mean_ci  # noqa: E402
from hds.logger import print_table  # noqa: E402
from hds.networks import make_policy  # noqa: E402
from hds.results import PlantTime  # noqa: E402
from hds.simulators import Simulator  # noqa: E402
from hds.utils import cli  # noqa: E402
from hds.utils.io import atomic_write_json, read_json  # noqa: E402

log = logging.getLogger("hds")


def record(cfg: Config, env, plant, params, key, scale: float, env_cfg=None) -> Dataset:
    """One round's data (hds.data.acquire.deployed_and_excited): the policy (the batch's first
    run) deployed from the task's initial states, and open-loop excitation whose amplitudes
    rise to `scale` of the half range (discover.excitation = designed: designed on env_cfg,
    the simulator corrected so far)."""
    from hds.discover.design import excitation_controls
    from hds.dynamics import excite

    horizon = env.task.horizon
    first = jax.tree.map(lambda x: x[0], params)
    act = jax.jit(make_policy(cfg.algo.hidden, env.sim).apply)
    excitation = dataclasses.replace(
        cfg.dynamics,
        episodes=cfg.loop.excitation_episodes,
        horizon=horizon,
        excitation_scale=scale,
    )

    def controls(k_u, q0, qd0, deployed):
        return excitation_controls(
            cfg.discover,
            env_cfg or cfg.env,
            env.sim.dt,
            horizon,
            q0,
            qd0,
            scale,
            lambda: excite(excitation, env, k_u),
            deployed,
        )

    return deployed_and_excited(
        plant,
        env.task,
        key,
        lambda o: np.asarray(act(first, o)),
        cfg.loop.deploy_episodes,
        cfg.loop.excitation_episodes,
        horizon,
        controls,
    )


def excite_until_identifiable(cfg: Config, env, plant, params, key, data_so_far, env_cfg=None):
    """A round's data (`record`), more and stronger while the data so far cannot identify
    what they could (hds.discover.record_until_identifiable). Returns (every dataset so far,
    the last amplitude, notes saying what was done and why)."""
    from hds.discover import record_until_identifiable

    def record_attempt(scale, attempt):
        nonlocal key
        key, sub = jax.random.split(key)
        return record(cfg, env, plant, params, sub, scale, env_cfg)

    return record_until_identifiable(
        record_attempt, cfg.env, cfg.discover, cfg.dynamics.excitation_scale, data_so_far
    )


def round_config(cfg: Config, r: int) -> Config:
    """Round 0 trains as configured. Each later round trains loop.epochs (0: algo.epochs).
    Warm-started (loop.warm_start) from a policy that already solves the task, its
    continuation (anneal.effect_ramp) begins at once and lasts as long as configured: waiting
    first, as a policy learning from scratch must, would spend the round's first epochs on the
    simulator without the effects it was corrected with. The ramp still waits for a
    warm-started policy that does not solve the task (anneal.ramp_when_solved). A round from
    scratch keeps round 0's continuation."""
    if r == 0:
        return cfg
    anneal = cfg.anneal
    if cfg.loop.warm_start:
        begin, end = cfg.anneal.effect_ramp
        anneal = dataclasses.replace(cfg.anneal, effect_ramp=[0.0, end - begin])
    algo = dataclasses.replace(cfg.algo, epochs=cfg.loop.epochs or cfg.algo.epochs)
    return dataclasses.replace(cfg, algo=algo, anneal=anneal)


def afresh_config(cfg: Config, r: int) -> Config:
    """Round r's training for a run whose warm start failed: from scratch, with the round's
    continuation (its effects waiting until the policy balances), for round 0's epochs and
    rounds 1..r's, so that the policy it keeps has had the loop's budget so far."""
    round_cfg = round_config(cfg, r)
    epochs = cfg.algo.epochs + r * round_cfg.algo.epochs
    return dataclasses.replace(round_cfg, algo=dataclasses.replace(round_cfg.algo, epochs=epochs))


# The settings a run's training does not read, for loop.start_from: where and how its policies
# are evaluated, what the loop's later rounds do, and the learned model, which the loop fits
# from round 1 on (round 0 trains without one). Every other setting must be the loop's.
NOT_TRAINED_ON = (
    "real",
    "eval_plants",
    "eval_episodes",
    "eval_seed",
    "oracle",
    "gif",
    "objective",
    "name",
    "checkpoints_kept",
    "paths",
    "loop",
    "discover",
    "dynamics",
)


def round_zero_source(cfg: Config) -> Path | None:
    """The checkpoints round 0 restores instead of training: those of loop.start_from's
    finished run, whose training must be round 0's (the nominal simulator, no learned model,
    every setting in `NOT_TRAINED_ON`'s complement the loop's); None without it. Raises
    ValueError, one line naming the problem, before anything compiles."""
    if not cfg.loop.start_from:
        return None
    start = Path(cfg.loop.start_from)
    recorded = start / rundir.CONFIG
    if not (start / "summary.json").is_file() or not recorded.is_file():
        raise ValueError(
            f"loop.start_from: {start} holds no finished run (summary.json, {rundir.CONFIG}); "
            "point it at a finished hds.run directory, or leave it out to train round 0 here"
        )
    try:
        theirs = load_config(recorded)
    except ValueError as err:
        raise ValueError(f"loop.start_from: {recorded}: {err}") from None
    if theirs.simulator != "nominal" or theirs.uses_model():
        model = " and a learned model" if theirs.uses_model() else ""
        raise ValueError(
            f"loop.start_from: {start} trained on the {theirs.simulator} simulator{model}; "
            "round 0 trains on the nominal simulator alone: point it at such a run "
            "(simulator=nominal, dynamics=none)"
        )
    changed = rundir.differences(
        OmegaConf.structured(theirs), OmegaConf.structured(cfg), ignored=NOT_TRAINED_ON
    )
    if changed:
        raise ValueError(
            f"loop.start_from: {start} trained with other settings than this loop's round 0 "
            f"({'; '.join(changed)}); give the loop its settings, or leave loop.start_from out"
        )
    source = start / "checkpoints" / theirs.algo.name
    if not source.is_dir():
        raise ValueError(
            f"loop.start_from: {start} has no checkpoints of {theirs.algo.name} ({source}); "
            "train it again with checkpoints, or leave loop.start_from out"
        )
    return source


def run_loop(cfg: Config, out_dir: Path, hooks: experiment.Hooks | None = None) -> list[dict]:
    """Every round of the loop (see the module's doc); returns the rounds' reports. With
    loop.start_from, round 0 restores that run's policies (`round_zero_source`)."""
    round_zero = round_zero_source(cfg)  # refused, where it is, before anything compiles
    out_dir = Path(out_dir)
    hooks = hooks or experiment.Hooks()
    enable_compilation_cache()
    plants = experiment.run_plants(cfg)
    plant = plants[0]
    env_cfg, params, data, rounds = cfg.env, None, [], []
    spent = PlantTime()
    key = jax.random.PRNGKey(cfg.seed + 7919)  # the loop's data, apart from training's keys
    for r in range(cfg.loop.rounds + 1):
        key, round_key = jax.random.split(key)
        rdir = out_dir / "rounds" / str(r)
        found, notes, scale, recorded = [], [], None, PlantTime()
        if r > 0:
            if (rdir / "data.npz").is_file():  # recorded before the loop was stopped
                new = [load(rdir / "data.npz")]
                recording = read_json(rdir / "excitation.json")
                scale = recording["scale"]
                # the noise the skipped recording drew: later evaluations measure what they
                # measured in the uninterrupted run (directories written before: not kept)
                if "plant_noise" in recording:
                    plant.set_noise_state(recording["plant_noise"])
            else:
                env = make_env(env_cfg)
                data_all, scale, notes = excite_until_identifiable(
                    cfg, env, plant, params, round_key, data, env_cfg
                )
                new = data_all[len(data) :]
                save(concatenate(new), rdir / "data.npz")
                atomic_write_json(
                    rdir / "excitation.json",
                    {"scale": scale, "notes": notes, "plant_noise": plant.noise_state()},
                )
            data = [*data, *new]
            recorded = plant_time(cfg, concatenate(new))
            spent += recorded
            env_cfg, found = discover_round(cfg, concatenate(data), rdir)
        start = params if cfg.loop.warm_start else None
        restore = round_zero if r == 0 else None
        report = train_round(cfg, r, env_cfg, start, data, rdir, hooks, plants, restore)
        params = report.pop("params")
        report |= {"round": r, "effects": found, "excitation_scale": scale, "notes": notes}
        report["data_episodes"] = int(sum(d.n_episodes for d in data))
        report["plant_time"] = recorded.to_json()
        report["plant_time_so_far"] = spent.to_json()
        atomic_write_json(rdir / "round.json", report)  # the round's whole report, data used too
        rounds.append(report)
        if r > 0 and not goes_on(rounds[-2], report):
            log.info("round %d: the real return no longer improves; the loop stops", r)
            break
        if r > 0 and (failed := plant_failures(report)):
            log.info(
                "round %d: seeds %s solve the corrected simulator and fail on the plant; the "
                "loop goes on to record them",
                r,
                failed,
            )
    result = result_round(rounds)
    atomic_write_json(
        out_dir / "loop.json",
        {"rounds": rounds, "result_round": result, "plant_time": spent.to_json()},
    )
    plots.save(plots.loop_rounds(rounds), out_dir / "plots" / "loop_rounds.png")
    if hooks.console:
        print_table([round_row(x) for x in rounds], title=f"{cfg.name}: the sim2real loop")
        (real, lo, hi) = rounds[result]["real_return"]
        print(
            f"the loop's policy: round {result}'s (real return {real:.4g} [{lo:.4g}, {hi:.4g}]), "
            f"in {out_dir / 'rounds' / str(result)}"
        )
    return rounds


def goes_on(before: dict, after: dict) -> bool:
    """Whether the loop records another round after `after` (the round reports of two
    successive rounds): while the real return rises beyond the rounds' intervals (`improved`),
    or while a policy that solves its simulator fails on the plant (`plant_failures`)."""
    return improved(before, after) or bool(plant_failures(after))


def result_round(rounds: list[dict]) -> int:
    """The round whose policies the loop leaves: the latest that no other round beats beyond
    the rounds' intervals (`improved`). A rise or a fall within the intervals keeps the later
    round: choosing the better of two on the evaluation that measured them would favour noise.
    The round with the best mean is never beaten (nor is a round by itself), so there always
    is one."""
    return max(
        k for k, kept in enumerate(rounds) if not any(improved(kept, other) for other in rounds)
    )


def plant_failures(report: dict) -> list[int]:
    """The seeds whose policy solves the task on its simulator and fails it on the plant (the
    task's `solved_at`; none where the task has none): a gap in the model where it matters,
    which the next round's deployments record, so the loop goes on while there is one, even
    where the real return's mean did not rise beyond the intervals (with 3 seeds, one failing
    seed hides any rise)."""
    return [
        row.get("seed", k)
        for k, row in enumerate(report["rows"])
        if row.get("solved_sim") is True and row.get("solved_real") is False
    ]


def plant_time(cfg: Config, data: Dataset) -> PlantTime:
    """The plant time a round's recorded data cost: each of its records (`record`; active
    excitation adds records) deployed loop.deploy_episodes, then excited
    loop.excitation_episodes, every episode `data.horizon` steps of `data.dt`."""
    return PlantTime.of_round(
        data.n_episodes,
        data.horizon,
        data.dt,
        cfg.loop.deploy_episodes,
        cfg.loop.excitation_episodes,
    )


def discover_round(cfg: Config, data: Dataset, rdir: Path):
    """Gap discovery on all data so far: the corrected env config and the named effects."""
    from hds.discover import corrected_env, discover, write_report

    result = discover(data, cfg.env, cfg.discover)
    write_report(result, cfg.env, rdir / "discovery", cfg.discover.plot_episodes, cfg.discover.bins)
    return env_config(corrected_env(cfg.env, result)), [e.to_json() for e in result.missing_effects]


def train_round(cfg, r, env_cfg, params, data, rdir, hooks, plants, restore=None) -> dict:
    """Train (warm-started from `params`, None: from scratch) on the round's simulator and, for HDS,
    a model refitted on the loop's data; evaluate on `plants` (the runs' plants). A round
    trained before is restored from its checkpoints, else from `restore` (another run's of the
    same training) where given. Returns its report (run_loop adds the data used and writes
    round.json) and the trained parameters (`params`)."""
    round_cfg = round_config(cfg, r)
    env = make_env(env_cfg)
    model, model_report = None, {}
    if r > 0 and cfg.uses_model():
        model, model_report = round_model(cfg, env_cfg, env, concatenate(data), rdir)
    method = f"loop{r}"
    simulator = Simulator(env)

    def train_and_evaluate(train_cfg, out_dir, init_params, restore_from=None):
        training, rows, _ = experiment.train_and_evaluate(
            train_cfg,
            method,
            simulator,
            out_dir,
            plants,
            hooks,
            model,
            init_params,
            restore_from=restore_from,
        )
        return training.params, rows

    trained, rows = train_and_evaluate(round_cfg, rdir, params, restore)
    # A warm-started run that still fails on the corrected simulator trains again from
    # scratch, its effects waiting until it balances, for every epoch the loop has spent on it
    # (`afresh_config`): warm-started from a policy that the named 2-step delay topples, every
    # seed failed, and a policy from scratch on a round's budget alone lags the oracle's.
    afresh = np.array(
        [params is not None and row.solved_sim is not None and not row.solved_sim for row in rows]
    )
    if afresh.any():
        afresh_cfg = afresh_config(cfg, r)
        log.info(
            "round %d: runs %s fail the task on the corrected simulator, warm-started; they "
            "train again from scratch, %d epochs",
            r,
            np.flatnonzero(afresh).tolist(),
            afresh_cfg.algo.epochs,
        )
        again, rows_again = train_and_evaluate(afresh_cfg, rdir / "afresh", None)
        trained = jax.tree.map(
            lambda new, old: np.where(np.reshape(afresh, (-1,) + (1,) * (old.ndim - 1)), new, old),
            again,
            trained,
        )
        rows = [b if a else row for a, row, b in zip(afresh, rows, rows_again)]
    real, gap = mean_ci([row.real_return for row in rows]), mean_ci([row.gap for row in rows])
    report = {"rows": [row.to_json() for row in rows], "real_return": real, "gap": gap}
    if afresh.any():
        report["trained_afresh"] = np.flatnonzero(afresh).tolist()
    if model_report:
        report["model"] = {
            k: model_report.get(k) for k in ("used", "simulator_effects", "multistep")
        }
    if "not_used_because" in model_report:
        report["model_not_used_because"] = model_report["not_used_because"]
    return report | {"params": trained}


def round_model(cfg: Config, env_cfg, env, data: Dataset, rdir: Path):
    """A round's learned model (HDS), fitted on all the loop's data so far (every round's
    policy deployed on the plant, and its excitation) with `env`, the simulator the round
    trains on (env_cfg: the corrected one), as its base: dynamics=residual (the hybrid) learns
    what the corrected simulator still misses, not what discovery already named. Returns
    (model, report); the model is None, the report saying why, where it predicts the held-out
    episodes no better than that simulator alone (dynamics.require_better)."""
    from hds.dynamics import build

    save(data, rdir / "model_data.npz")
    dyn = dataclasses.replace(cfg.dynamics, data=str(rdir / "model_data.npz"))
    model, report = build(dyn, env, None, jax.random.PRNGKey(cfg.seed), rdir / "dynamics")
    report["simulator_effects"] = [f"{e.name}@{e.target}" for e in env_cfg.effects]
    return model, report


def improved(before: dict, after: dict) -> bool:
    """Whether the real return rose beyond the rounds' 95% intervals ([mean, low, high]): the
    new mean above the previous round's interval, or the previous mean below the new round's
    (one failing seed widens a round's interval enough to hide a rise from -209 to -8)."""
    (mean_before, _, high_before), (mean_after, low_after, _) = (
        before["real_return"],
        after["real_return"],
    )
    return mean_after > high_before or mean_before < low_after


def round_row(report: dict) -> dict:
    """A round of the loop as one row: named effects with their 95% intervals, the real
    return and its interval, the gap, the episodes of data so far and the plant time they
    cost (seconds deployed + excited; rounds written before it was reported: 0)."""
    names = ", ".join(
        f"{e['name']}@{e['target']} "
        + " ".join(
            f"{v:.3g} [{e['ci95'][k][0]:.3g}, {e['ci95'][k][1]:.3g}]"
            for k, v in e["params"].items()
        )
        for e in report["effects"]
    )
    (real, lo, hi), (gap, *_) = report["real_return"], report["gap"]
    return {
        "round": report["round"],
        "real_return": real,
        "interval": f"[{lo:.1f}, {hi:.1f}]",
        "gap": gap,
        "episodes": report["data_episodes"],
        "plant_s": "{deployment_s:.0f} + {excitation_s:.0f}".format(
            **PlantTime.from_json(report.get("plant_time_so_far")).to_json()
        ),
        "named": names or "-",
    }


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(dcfg) -> float:
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    hydra_dir = out_dir / HydraConfig.get().output_subdir
    with cli.one_line_errors(), rundir.claim(out_dir, dcfg, hydra_dir):  # locked
        cfg = validate(dcfg)  # every range check, before anything compiles
        check_planned(cfg, loop=True)  # its data past the limits: refused with the numbers
        rounds = run_loop(cfg, out_dir)
    return float(rounds[result_round(rounds)]["real_return"][0])


if __name__ == "__main__":
    before_hydra(loop=True)
    main()
