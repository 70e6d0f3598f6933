"""Trained policies as objects a researcher uses: load one from a run directory, call it on
observations (NumPy or JAX), evaluate it on any plant, export it to run without JAX.

    policy = hds.load_policy("outputs/runs/<name>/<time>", seed=0)
    model = policy.mj_model(); data = mujoco.MjData(model)
    data.ctrl[:] = policy(policy.observe(data)); mujoco.mj_step(model, data, policy.frames)
"""

from __future__ import annotations

import functools
import json
import logging
import shutil
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from hds import policy_store, simulators
from hds.config import Config, EnvConfig, RealConfig, load_config, run_label
from hds.data import initial_states
from hds.effects.apply import applied
from hds.envs import Env, make_env
from hds.envs.system import load_spec, resolve_xml
from hds.gap import MeanCI, mean_ci
from hds.networks import make_policy
from hds.real import Episodes, make_plant, rollout
from hds.utils.io import atomic_write_bytes, atomic_write_json

log = logging.getLogger("hds")

EXPORT_FORMAT = "hds-policy/1"
FORMATS = ("json", "onnx")  # hds.export's format=: json (policy.json + npz), onnx (also .onnx)
KB = ("kernel", "bias")  # each layer's arrays, as policy.npz names them: Dense_0_kernel, ...


@dataclass(frozen=True, eq=False)
class Policy:
    """One run's trained policy: `u = policy(obs)` maps observations [..., n_obs] (named
    `obs_names`) to controls [..., n_act] within `ctrl_range`. NumPy in, NumPy out (jitted);
    a JAX array in, a JAX array out (traceable, differentiable)."""

    module: object  # hds.networks.Policy (its flax module made on first use)
    params: dict  # its parameters (one run)
    env: EnvConfig  # the system and task the policy was trained for
    method: str  # the row label of the run (pods, hds+mlp, oracle, ...)
    run: dict  # its seed and swept settings
    epoch: int  # the epoch of the checkpoint it was restored from
    config: Config = field(repr=False)  # the whole run's config
    run_dir: Path | None = None

    def __repr__(self) -> str:  # the weights stay out: `policy.params` has them
        hidden = tuple(self.module.hidden)
        return (
            f"Policy(method={self.method!r}, run={self.run}, epoch={self.epoch}, "
            f"system={Path(self.env.xml).name!r}, {len(self.obs_names)} observations -> "
            f"{len(self.action_names)} actions, hidden={hidden}, run_dir={str(self.run_dir)!r})"
        )

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
        plant to evaluate on: `hds.evaluate_policy(policy, plant=policy.training_plant())`."""
        from hds.real.brax_plant import BraxPlant

        kind = simulators.of(self.config, self.method)
        return BraxPlant(kind.restore(self.config, self.run_dir).env)

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
    from its config.yaml and saved policies (policies/<method>: the network's spec and
    parameters; hds.policy_store), or, in a directory written before those were saved, its
    latest checkpoint. No trainer is built. `method`: whose policy (default: the run's own
    method, e.g. pods or hds+mlp; an oracle trained beside it is `oracle`); `seed` and swept
    settings (e.g. step_size=0.04) pick the run of a batch (default: the first)."""
    run_dir = Path(run_dir)
    cfg = run_config(run_dir)
    method = method or simulators.method_name(cfg)
    trained = set()
    for root in (run_dir / "policies", run_dir / "checkpoints"):
        trained |= {p.name for p in root.iterdir() if p.is_dir()} if root.is_dir() else set()
    if method not in trained:
        raise FileNotFoundError(
            f"no checkpoint of method '{method}' and no saved policy of it in {run_dir}; it "
            f"has {sorted(trained) or 'none'}: choose one with method=..., or train the run first"
        )
    index = _pick_run(cfg, seed, setting)
    if (run_dir / "policies" / method / "policy.json").is_file():
        module, params, epochs = policy_store.load(run_dir / "policies" / method)
    else:  # an older run directory: its last checkpoint, read as stored
        params, epochs = policy_store.from_checkpoint(run_dir / "checkpoints" / method)
        module = make_policy(cfg.algo.hidden, make_env(cfg.env).sim)
    epoch = int(epochs[index])
    if epoch < cfg.algo.epochs:
        log.warning(
            "%s: %s is at epoch %d of %d (unfinished)", run_dir, method, epoch, cfg.algo.epochs
        )
    params = jax.tree.map(lambda x: jnp.asarray(x[index]), params)
    return Policy(module, params, cfg.env, method, cfg.runs()[index], epoch, cfg, run_dir)


# --- evaluation ----------------------------------------------------------------------------------


@dataclass
class Evaluation:
    """A policy's episodes on one plant, from the shared evaluation initial states."""

    episodes: Episodes  # obs [E, T+1, n_obs], actions [E, T, n_act], rewards [E, T]
    plant: dict  # plant, friction_gap, effects

    @property
    def returns(self) -> np.ndarray:
        return self.episodes.returns

    def mean_ci(self) -> MeanCI:
        """Mean return and its 95% Student-t interval over episodes: (mean, low, high)."""
        return mean_ci(self.returns)

    def to_json(self) -> dict:
        mean, lo, hi = self.mean_ci()
        return {
            "plant": self.plant,
            "returns": self.returns.tolist(),
            "mean": mean,
            "ci95": [lo, hi],
        }


def evaluate_policy(
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
    """The plant as evaluation.json records it: its effects with the values it applies (a
    friction at real.friction_gap=2 records twice its configured force)."""
    effects = applied(real.effects, real.friction_gap)
    return {"plant": real.plant, "friction_gap": real.friction_gap, "effects": effects}


def trained_on(policy: Policy) -> tuple[dict, EnvConfig, list[dict]]:
    """What `policy` trained on, as policy.json records it (the simulator's kind: nominal,
    corrected by gap discovery, randomized or the plant's own dynamics for the oracle; its
    effects with the values applied), and that system's env config and effects, for its MJCF."""
    kind = simulators.of(policy.config, policy.method)
    return kind.trained_on(policy.config, policy.run, policy.run_dir)


# --- export --------------------------------------------------------------------------------------


def export_policy(policy: Policy, out_dir: str | Path, format: str = "json") -> Path:
    """Write `policy` as a self-contained directory that runs without JAX: policy.npz (the
    weights), policy.json (the contract: observations, actions, control range, dt, how
    observations enter the network, what the policy trained on), the MJCF of the system it
    trained on, and numpy_policy.py (NumPy inference: `numpy_policy.load(dir)(obs)`); with
    format="onnx" also policy.onnx (input `obs`, output `action`; docs/export.md)."""
    check_format(format)
    out_dir = Path(out_dir)
    layers = policy.params["params"]
    names = sorted(layers, key=lambda n: int(n.rsplit("_", 1)[1]))  # Dense_0, Dense_1, ...
    weights = [(np.asarray(layers[n]["kernel"]), np.asarray(layers[n]["bias"])) for n in names]
    buffer = _npz({f"{n}_{p}": w for n, pair in zip(names, weights) for p, w in zip(KB, pair)})
    atomic_write_bytes(out_dir / "policy.npz", buffer)
    trained, env_cfg, effects = trained_on(policy)
    mjcf_name, mjcf = _mjcf(policy, trained["simulator"], env_cfg, effects)
    contract = {
        "format": EXPORT_FORMAT,
        "method": policy.method,
        "run": policy.run,
        "epoch": policy.epoch,
        "trained_on": {**trained, "mjcf": mjcf_name},
        "observations": list(policy.obs_names),
        "actions": list(policy.action_names),
        "control_range": np.asarray(policy.ctrl_range, float).tolist(),
        "dt": policy.dt,
        "timestep": policy.env.timestep,
        "frames_per_step": policy.env.frames_per_step,
        "mjcf": mjcf_name,
        # the network's input: observations as they are (no normalisation), except that each
        # hinge angle enters as (sin, cos): [q of non-hinges, sin(hinges), cos(hinges), qd]
        "normalisation": "none",
        "hinge_angles": [bool(a) for a in policy.module.angular],
        "layers": [
            {"kernel": f"{n}_kernel", "bias": f"{n}_bias", "activation": "tanh"} for n in names
        ],
        "output": "mid + half * tanh(last layer): mid, half of each control range",
    }
    if format == "onnx":
        from hds import onnx_policy

        metadata = {
            "format": EXPORT_FORMAT,
            "method": policy.method,
            "observations": ",".join(policy.obs_names),
            "actions": ",".join(policy.action_names),
            "dt": repr(policy.dt),
            "trained_on": json.dumps(contract["trained_on"]),
        }
        model = onnx_policy.build(weights, policy.module.angular, policy.ctrl_range, metadata)
        atomic_write_bytes(out_dir / "policy.onnx", model)
        contract["onnx"] = {
            "file": "policy.onnx",
            "input": onnx_policy.INPUT,
            "output": onnx_policy.OUTPUT,
            "opset": onnx_policy.OPSET,
        }
    atomic_write_json(out_dir / "policy.json", contract)
    atomic_write_bytes(out_dir / mjcf_name, mjcf)
    shutil.copyfile(Path(__file__).with_name("numpy_policy.py"), out_dir / "numpy_policy.py")
    return out_dir


def check_format(format: str) -> None:
    if format not in FORMATS:
        raise ValueError(
            f"format={format!r} is not an export format; choose json (policy.json, policy.npz, "
            "numpy_policy.py) or onnx (the same and policy.onnx)"
        )


def _mjcf(policy: Policy, kind: str, env_cfg, effects: list[dict]) -> tuple[str, bytes]:
    """(file name, bytes) of the MJCF of the system the policy trained on: the env's own file
    as it is when it trained on that alone, else that MJCF with the MuJoCo-native equivalents
    of its effects written in and a comment naming those MJCF cannot express."""
    xml = resolve_xml(env_cfg.xml)
    if not effects and env_cfg.xml == policy.env.xml:
        return xml.name, xml.read_bytes()
    from hds.real.mujoco_plant import mjcf_text

    source = f"The {kind} simulator policy {policy.method} trained on (hds.export)"
    return f"{xml.stem}_{kind}.xml", mjcf_text(env_cfg, effects, source=source).encode()


def _npz(arrays: dict) -> bytes:
    import io

    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def __getattr__(name: str):
    """`evaluate` and `export`, the functions' names until 2026-11-27 (a DeprecationWarning)."""
    renamed = {"evaluate": "evaluate_policy", "export": "export_policy"}
    if name not in renamed:
        raise AttributeError(f"module 'hds.policy' has no attribute '{name}'")
    warnings.warn(f"hds.policy.{name} is deprecated: use {renamed[name]}", DeprecationWarning, 2)
    return globals()[renamed[name]]
