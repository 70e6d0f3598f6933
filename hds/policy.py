"""Trained policies as objects a researcher uses: load one from a run directory, call it on
observations (NumPy or JAX), evaluate it on any plant, export it to run without JAX.

    policy = hds.load_policy("outputs/runs/<name>/<time>", seed=0)
    model = policy.mj_model(); data = mujoco.MjData(model)
    data.ctrl[:] = policy(policy.observe(data)); mujoco.mj_step(model, data, policy.frames)
"""

from __future__ import annotations

import functools
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from hds.algo.pods import make_train
from hds.checkpoint import Checkpoints
from hds.config import Config, EnvConfig, RealConfig, load_config, run_label
from hds.data import initial_states
from hds.envs import Env, make_env
from hds.envs.system import load_spec, resolve_xml
from hds.evaluation import mean_ci
from hds.experiment import abstract_state, method_name, simulator_of
from hds.real import Episodes, make_plant, rollout
from hds.utils.io import atomic_write_bytes, atomic_write_json

log = logging.getLogger("hds")

EXPORT_FORMAT = "hds-policy/1"


@dataclass(frozen=True, eq=False)
class Policy:
    """One run's trained policy: `u = policy(obs)` maps observations [..., n_obs] (named
    `obs_names`) to controls [..., n_act] within `ctrl_range`. NumPy in, NumPy out (jitted);
    a JAX array in, a JAX array out (traceable, differentiable)."""

    module: object  # hds.networks.Policy (flax)
    params: dict  # its parameters (one run)
    env: EnvConfig  # the system and task the policy was trained for
    method: str  # the row label of the run (pods, hds+mlp, oracle, ...)
    run: dict  # its seed and swept settings
    epoch: int  # the epoch of the checkpoint it was restored from
    config: Config = field(repr=False)  # the whole run's config
    run_dir: Path | None = None

    def __call__(self, obs):
        if isinstance(obs, jax.Array):
            return self.module.apply(self.params, obs)
        return np.asarray(self._jitted(self.params, jnp.asarray(obs, jnp.float32)))

    @functools.cached_property
    def _jitted(self):
        return jax.jit(self.module.apply)

    @functools.cached_property
    def simulator(self) -> Env:
        """The nominal simulator of the run's env config (its task gives the rewards)."""
        return make_env(self.env)

    def training_plant(self):
        """The simulator this policy trained on (nominal, corrected or the oracle's), as a
        plant to evaluate on: `hds.evaluate(policy, plant=policy.training_plant())`."""
        from hds.real.brax_plant import BraxPlant

        return BraxPlant(simulator_of(self.config, self.run_dir, self.method)[0])

    @property
    def obs_names(self) -> tuple[str, ...]:
        return self.simulator.sim.obs_names

    @property
    def action_names(self) -> tuple[str, ...]:
        return self.simulator.sim.action_names

    @property
    def ctrl_range(self) -> np.ndarray:
        return self.simulator.sim.ctrl_range

    @property
    def frames(self) -> int:
        """MuJoCo steps per control step (the policy acts every dt = timestep * frames)."""
        return self.env.frames_per_step

    @property
    def dt(self) -> float:
        return self.env.timestep * self.env.frames_per_step

    def mj_model(self) -> mujoco.MjModel:
        """The nominal C MuJoCo model of the policy's system, at the simulator's timestep."""
        return load_spec(self.env.xml, self.env.timestep).compile()

    def observe(self, data: mujoco.MjData) -> np.ndarray:
        """The policy's observation of a MuJoCo state: [qpos, qvel] (hinge and slide joints)."""
        return np.concatenate([data.qpos, data.qvel]).astype(np.float32)


def _pick_run(cfg: Config, seed: int | None, setting: dict) -> int:
    """The index in the run's batch of the run with this seed and swept settings."""
    runs = cfg.runs()
    unknown = set(setting) - {k for k, _ in cfg.sweep.items()}
    if unknown:
        raise ValueError(
            f"{sorted(unknown)} not swept in this run; its runs are {[run_label(r) for r in runs]}"
        )
    matches = [
        i
        for i, r in enumerate(runs)
        if (seed is None or r["seed"] == seed)
        and all(np.isclose(r[k], float(v)) for k, v in setting.items())
    ]
    if len(matches) == 1 or (matches and seed is None and not setting):
        return matches[0]
    which = "none" if not matches else f"{len(matches)}"
    raise ValueError(
        f"{which} of this run's runs match seed={seed} {setting or ''}; its runs are "
        f"{[run_label(r) for r in runs]}: give seed= and each swept setting"
    )


def run_config(run_dir: Path) -> Config:
    """The validated config of a finished run directory (its config.yaml)."""
    if not (Path(run_dir) / "config.yaml").is_file():
        raise FileNotFoundError(
            f"{run_dir}/config.yaml not found: give the directory of one run (a sweep's job "
            "directory), which holds config.yaml and checkpoints/"
        )
    return load_config(Path(run_dir) / "config.yaml")


def load_policy(run_dir: str | Path, method: str | None = None, seed: int | None = None, **setting):
    """The trained policy of one run of a run directory (`python -m hds.run`, `hds.train`),
    from its config.yaml and latest checkpoint. `method`: whose policy (default: the run's own
    method, e.g. pods or hds+mlp; an oracle trained beside it is `oracle`); `seed` and swept
    settings (e.g. step_size=0.04) pick the run of a batch (default: the first)."""
    run_dir = Path(run_dir)
    cfg = run_config(run_dir)
    root = run_dir / "checkpoints"
    trained = sorted(p.name for p in root.iterdir() if p.is_dir()) if root.is_dir() else []
    method = method or method_name(cfg)
    if method not in trained:
        raise FileNotFoundError(
            f"no checkpoint of method '{method}' in {root}; it has {trained or 'none'}: "
            "choose one with method=..., or train the run first"
        )
    index = _pick_run(cfg, seed, setting)
    trainer = make_train(cfg, make_env(cfg.env))
    state, _ = Checkpoints(root / method).restore(abstract_state(cfg, trainer))
    epoch = int(state.epoch[index])
    if epoch < cfg.algo.epochs:
        log.warning(
            "%s: %s is at epoch %d of %d (unfinished)", run_dir, method, epoch, cfg.algo.epochs
        )
    params = jax.tree.map(lambda x: x[index], trainer.final_policy(state))
    return Policy(trainer.policy, params, cfg.env, method, cfg.runs()[index], epoch, cfg, run_dir)


# --- evaluation ----------------------------------------------------------------------------------


@dataclass
class Evaluation:
    """A policy's episodes on one plant, from the shared evaluation initial states."""

    episodes: Episodes  # obs [E, T+1, n_obs], actions [E, T, n_act], rewards [E, T]
    plant: dict  # plant, friction_gap, effects

    @property
    def returns(self) -> np.ndarray:
        return self.episodes.returns

    def mean_ci(self) -> tuple[float, float, float]:
        """Mean return and its 95% Student-t interval over episodes."""
        return mean_ci(self.returns)

    def to_json(self) -> dict:
        mean, lo, hi = self.mean_ci()
        return {
            "plant": self.plant,
            "returns": self.returns.tolist(),
            "mean": mean,
            "ci95": [lo, hi],
        }


def evaluate(
    policy: Policy,
    real: RealConfig | None = None,
    episodes: int | None = None,
    seed: int | None = None,
    plant=None,
) -> Evaluation:
    """Run `policy` on a plant: `real` (a RealConfig, e.g. `hds.compose(["real=brax",
    "real.friction_gap=2"]).real`; default: the run's own plant), or any `plant` object with
    reset/step/state (hds.real). `episodes` and `seed` default to the run's eval_episodes and
    eval_seed, the initial states its summary.json was measured from."""
    cfg = policy.config
    real = real or cfg.real
    env = policy.simulator
    if plant is None:
        plant = make_plant(real, policy.env)
        description = _describe(real)
    else:
        description = {"plant": type(plant).__name__}
    q0, qd0 = initial_states(
        env.task, cfg.eval_seed if seed is None else seed, episodes or cfg.eval_episodes
    )
    return Evaluation(rollout(plant, env.task, q0, qd0, policy, env.task.horizon), description)


def _describe(real: RealConfig) -> dict:
    effects = [{"name": e.name, "target": e.target, "params": dict(e.params)} for e in real.effects]
    return {"plant": real.plant, "friction_gap": real.friction_gap, "effects": effects}


# --- export --------------------------------------------------------------------------------------


def export(policy: Policy, out_dir: str | Path) -> Path:
    """Write `policy` as a self-contained directory that runs without JAX: policy.npz (the
    weights), policy.json (the contract: observations, actions, control range, dt, how
    observations enter the network), the MJCF of its system, and numpy_policy.py (NumPy
    inference: `numpy_policy.load(dir)(obs)`)."""
    out_dir = Path(out_dir)
    layers = policy.params["params"]
    names = sorted(layers, key=lambda n: int(n.rsplit("_", 1)[1]))  # Dense_0, Dense_1, ...
    buffer = _npz({f"{n}_{p}": np.asarray(layers[n][p]) for n in names for p in ("kernel", "bias")})
    atomic_write_bytes(out_dir / "policy.npz", buffer)
    xml = resolve_xml(policy.env.xml)
    contract = {
        "format": EXPORT_FORMAT,
        "method": policy.method,
        "run": policy.run,
        "epoch": policy.epoch,
        "observations": list(policy.obs_names),
        "actions": list(policy.action_names),
        "control_range": np.asarray(policy.ctrl_range, float).tolist(),
        "dt": policy.dt,
        "timestep": policy.env.timestep,
        "frames_per_step": policy.env.frames_per_step,
        "mjcf": xml.name,
        # the network's input: observations as they are (no normalisation), except that each
        # hinge angle enters as (sin, cos): [q of non-hinges, sin(hinges), cos(hinges), qd]
        "normalisation": "none",
        "hinge_angles": [bool(a) for a in policy.module.angular],
        "layers": [
            {"kernel": f"{n}_kernel", "bias": f"{n}_bias", "activation": "tanh"} for n in names
        ],
        "output": "mid + half * tanh(last layer): mid, half of each control range",
    }
    atomic_write_json(out_dir / "policy.json", contract)
    atomic_write_bytes(out_dir / xml.name, xml.read_bytes())
    shutil.copyfile(Path(__file__).with_name("numpy_policy.py"), out_dir / "numpy_policy.py")
    return out_dir


def _npz(arrays: dict) -> bytes:
    import io

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()
