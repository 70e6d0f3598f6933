"""What a method trains on: the registry of simulator kinds, the config's `simulator=`.

Each kind is one class registered under its name, in the style of MuJoCo Playground's registry
(`load(name)`); it builds the method's training simulator from the config, restores the same
from a finished run directory (no data measured again), labels the run's rows and says what
policy.json records. Domain randomization is a function the kind hands to the trainer
(`Simulator.randomization`, as brax's `randomization_fn`), not a flag the trainer reads.

    kind = simulators.of(cfg)                   # simulators.load(cfg.simulator)
    built = kind.build(cfg, env, plant, out_dir)  # Simulator(env, effects, randomization, report)
    kind.label(cfg)                             # pods, hds+mlp, pods_cl+corrected, oracle, ...
    kind.restore(cfg, run_dir).env              # what the finished run trained on

The names of the kinds are declared in hds.config.kinds, the one list a config is validated
against before anything here is imported; `load(name)` builds the class declared there. A new
kind is one subclass of `SimulatorKind` (its `name`, `about`, `build` and `restore`) decorated
with `@register`, which declares its name too (docs/simulators.md).
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp

from hds.algo.randomize import Randomization, randomization, randomized_env
from hds.config import Config, env_config, kinds
from hds.effects.apply import applied, place
from hds.envs import Env, make_env

log = logging.getLogger("hds")


@dataclass(frozen=True)
class Simulator:
    """What a method trains on: the env, each run's effect parameters of it stacked [n_runs,
    ...] (None: the env's own), the randomization the trainer draws each rollout's effect
    parameters with (None: none), and a JSON-ready report of how it was built (gap
    discovery's findings; {} when nothing was measured)."""

    env: Env
    effects: object = None
    randomization: Randomization | None = None
    report: dict = field(default_factory=dict)


class SimulatorKind:
    """One kind of training simulator. `name`: the config's simulator= value (the name it is
    declared under in hds.config.kinds); `about`: one line, as policy.json records it; `tags`:
    what the rows' label adds to the method's; `discovers`: built by gap discovery on data
    measured on the plant (declared with the name: the checks read it before this is built)."""

    name: str = ""
    discovers: bool = False
    about: str = ""
    tags: tuple[str, ...] = ()

    def label(self, cfg: Config) -> str:
        """The label of the run's rows: its algorithm, learned model and simulator's tags."""
        parts = [cfg.algo.name]
        if cfg.uses_model():
            parts.append(cfg.dynamics.model)
        return "+".join([*parts, *self.tags])

    def build(self, cfg: Config, env: Env, plant, out_dir: Path) -> Simulator:
        """The training simulator of a new run in out_dir; `env`: the nominal simulator of
        cfg.env, `plant`: the batch's plant (for kinds that measure data on it). Kinds that
        measure nothing build what they restore."""
        return self.restore(cfg, out_dir)

    def restore(self, cfg: Config, run_dir: Path) -> Simulator:
        """The training simulator of a finished run, from what the run wrote."""
        raise NotImplementedError

    def recorded_as(self) -> str:
        """The kind's name in policy.json's trained_on."""
        return self.name

    def trained_on(self, cfg: Config, run: dict, run_dir: Path) -> tuple[dict, object, list]:
        """(what policy.json records, the env config of the system trained on, its effects
        with the values applied) of one run (`run`: its seed and swept settings)."""
        effects = applied(cfg.env.effects)
        return self.description(effects), cfg.env, effects

    def description(self, effects: list[dict]) -> dict:
        """policy.json's trained_on: the kind, the effects with the values applied, about."""
        return {"simulator": self.recorded_as(), "effects": effects, "about": self.about}


KINDS: dict[str, SimulatorKind] = {}  # the kinds built so far, by name


def register(cls: type[SimulatorKind]) -> type[SimulatorKind]:
    """Add a kind under its `name` (a class decorator): declared in hds.config.kinds, so that
    configs accept it from then on, and built."""
    if cls.name in KINDS:
        raise ValueError(f"simulator kind {cls.name!r} is registered twice")
    kinds.declare(cls.name, f"{cls.__module__}:{cls.__qualname__}", cls.discovers)
    KINDS[cls.name] = cls()
    return cls


def load(name: str) -> SimulatorKind:
    """The kind of this name, its class (declared in hds.config.kinds) built on first use."""
    if name not in KINDS:
        declared = kinds.kind(name)
        module, _, attribute = declared.where.partition(":")
        kind = getattr(importlib.import_module(module), attribute)()
        kind.name, kind.discovers = declared.name, declared.discovers
        KINDS[name] = kind
    return KINDS[name]


def of(cfg: Config, method: str | None = None) -> SimulatorKind:
    """The kind a run's `method` trained on: the config's own, or the plant's own dynamics for
    an oracle trained beside it (`oracle=true`)."""
    return load("real" if method == "oracle" else cfg.simulator)


def method_name(cfg: Config) -> str:
    """The label of the run's rows (pods, hds+mlp, pods+corrected, oracle)."""
    return of(cfg).label(cfg)


def friction_gap_of(cfg: Config, run: dict) -> float:
    return run.get("friction_gap", cfg.real.friction_gap)


# --- the kinds -----------------------------------------------------------------------------------
# each declared by name in hds.config.kinds (the names a config accepts), built by `load`


class Nominal(SimulatorKind):
    about = "the env's MJCF with its own effects (env.effects)"

    def build(self, cfg, env, plant, out_dir):
        return Simulator(env)

    def restore(self, cfg, run_dir):
        return Simulator(make_env(cfg.env))


class Randomized(SimulatorKind):
    """Domain randomization: the env with dr.effects placed at the middle of their ranges (its
    sim return is taken there), each rollout's drawn from the ranges."""

    about = "the env's MJCF with each rollout's effects drawn from ranges"
    tags = ("dr",)

    def restore(self, cfg, run_dir):
        env = randomized_env(cfg)
        return Simulator(env, randomization=randomization(cfg, env))

    def trained_on(self, cfg, run, run_dir):
        description, env_cfg, effects = super().trained_on(cfg, run, run_dir)
        description["randomized"] = [
            {"name": e.name, "target": e.target, "ranges": dict(e.ranges)} for e in cfg.dr.effects
        ]
        return description, env_cfg, effects


class Real(SimulatorKind):
    """The oracle: the simulator with the plant's own effects (friction smoothed so it
    differentiates), each run at its own friction gap."""

    about = "the plant's own effects (real.effects at the run's friction gap)"

    def label(self, cfg):
        return "oracle" if cfg.algo.name == "pods_cl" else f"{cfg.algo.name}+oracle"

    def recorded_as(self):
        return "oracle"

    def restore(self, cfg, run_dir):
        effects = list(cfg.real.effects)
        env = make_env(cfg.env, effects=effects, friction_gap=cfg.real.friction_gap)
        per_run = [place(effects, env.sim.targets, friction_gap_of(cfg, r))[1] for r in cfg.runs()]
        return Simulator(env, jax.tree.map(lambda *x: jnp.stack(x), *per_run))

    def trained_on(self, cfg, run, run_dir):
        effects = applied(cfg.real.effects, friction_gap_of(cfg, run))
        return self.description(effects), cfg.env, effects


class Corrected(SimulatorKind):
    """The simulator plus the effects gap discovery names on data measured on the plant."""

    about = "the env's MJCF with the effects gap discovery named on plant data"
    tags = ("corrected",)

    def build(self, cfg, env, plant, out_dir):
        env, report = corrected_simulator(cfg, env, plant, Path(out_dir))
        return Simulator(env, report=report)

    def restore(self, cfg, run_dir):
        return Simulator(make_env(corrected_env_config(run_dir)))

    def trained_on(self, cfg, run, run_dir):
        env_cfg = corrected_env_config(run_dir)
        effects = applied(env_cfg.effects)
        return self.description(effects), env_cfg, effects


def corrected_simulator(cfg: Config, env: Env, plant, out_dir: Path):
    """The simulator plus the effects gap discovery names on data measured on the plant
    (`discovery_data`); the data and the report go to out_dir/discovery. Returns (env,
    JSON-ready summary of the findings)."""
    from hds.data import save
    from hds.discover import corrected_env, discover, write_report

    data, source = discovery_data(cfg, env, plant)
    if source["data"] == "plant":
        for note in source["notes"]:
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


def discovery_data(cfg: Config, env: Env, plant):
    """The data the corrected simulator's discovery reads, and where they came from: the data
    a learned model of this seed is fitted on (dynamics.data, or recorded on the plant) and,
    while those cannot identify what more excitation would, more of it at doubled amplitude
    (hds.discover.record_until_identifiable). discover.excitation = designed: every record
    designed on the simulator (its nominal values: nothing is estimated yet) through the
    function the loop's rounds use, random steps the fallback (hds.discover.design)."""
    from hds.data import concatenate
    from hds.discover import record_until_identifiable
    from hds.discover.design import excitation_controls
    from hds.dynamics import collect_data, measured_data

    key = jax.random.split(jax.random.PRNGKey(cfg.seed))[0]
    data, source = measured_data(cfg.dynamics, env, plant, key)
    if source["data"] != "plant":
        return data, source
    designed = cfg.discover.excitation == "designed"

    def record(scale, attempt):  # the first: the learned model's data, unless designed
        if not attempt and not designed:
            return data
        dyn = dataclasses.replace(cfg.dynamics, excitation_scale=scale)

        def controls(q0, qd0, signal):
            h, dt = dyn.horizon, env.sim.dt
            return excitation_controls(cfg.discover, cfg.env, dt, h, q0, qd0, scale, signal, data)

        return collect_data(dyn, env, plant, jax.random.fold_in(key, attempt), controls)

    recorded, scale, notes = record_until_identifiable(
        record, cfg.env, cfg.discover, cfg.dynamics.excitation_scale
    )
    recorded = concatenate(recorded)
    source |= {"episodes": recorded.n_episodes, "excitation_scale": scale, "notes": notes}
    source["excitation"] = "designed" if designed else source["excitation"]
    return recorded, source


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
