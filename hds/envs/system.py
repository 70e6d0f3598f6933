"""The differentiable simulator: an MJCF on a Brax backend, with effects composed onto its step."""

from __future__ import annotations

import copy
import dataclasses
import functools
import importlib
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from hds.effects import EffectParams, EffectSet, place
from hds.envs import mjsystem
from hds.utils.pytree import pytree_dataclass
from hds.utils.quiet import quiet_brax
from hds.utils.runtime import cached_build

ASSETS = Path(__file__).parent / "assets"
BACKENDS = ("generalized", "spring", "positional", "mjx", "analytic", "tree")
_OWN_BACKENDS = ("analytic", "tree")  # modules of hds.envs; the others are brax pipelines
_FORCE_PREFIX = "hds_force_"  # the virtual motors through which effect forces enter


def resolve_xml(xml: str) -> Path:
    """An asset name (cartpole.xml) or a path to a user MJCF."""
    path = Path(xml).expanduser()
    if not path.is_file():
        path = ASSETS / xml
    if not path.is_file():
        assets = sorted(p.name for p in ASSETS.glob("*.xml"))
        raise FileNotFoundError(f"MJCF '{xml}' not found: give a file path or one of {assets}")
    return path


def load_spec(xml: str, timestep: float | None = None) -> mujoco.MjSpec:
    path = resolve_xml(xml)
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except ValueError as err:  # MuJoCo's parse errors name neither the file nor a fix
        raise ValueError(
            f"{path} is not a valid MJCF file ({' '.join(str(err).split())}): fix the file, "
            "or give another"
        ) from None
    if timestep is not None:
        spec.option.timestep = timestep
    return spec


def one_dof_joints(model: mujoco.MjModel) -> dict[str, int]:
    """{joint name: dof address} of the slide and hinge joints, where effects can act."""
    kinds = (int(mujoco.mjtJoint.mjJNT_SLIDE), int(mujoco.mjtJoint.mjJNT_HINGE))
    return {
        model.joint(j).name: int(model.jnt_dofadr[j])
        for j in range(model.njnt)
        if int(model.jnt_type[j]) in kinds
    }


def state_names(model: mujoco.MjModel) -> list[str]:
    """Observation names: q then qd of each joint, e.g. q_slider, q_hinge, qd_slider, qd_hinge."""
    qpos, qvel = [], []
    for j in range(model.njnt):
        name = model.joint(j).name
        nq = {0: 7, 1: 4}.get(int(model.jnt_type[j]), 1)
        nv = {0: 6, 1: 3}.get(int(model.jnt_type[j]), 1)
        qpos += [f"q_{name}"] if nq == 1 else [f"q_{name}_{k}" for k in range(nq)]
        qvel += [f"qd_{name}"] if nv == 1 else [f"qd_{name}_{k}" for k in range(nv)]
    return qpos + qvel


def hinge_mask(model: mujoco.MjModel) -> np.ndarray:
    """For each q entry: is it a hinge angle (whose error wraps around)?"""
    mask = np.zeros(model.nq, dtype=bool)
    for j in range(model.njnt):
        if int(model.jnt_type[j]) == int(mujoco.mjtJoint.mjJNT_HINGE):
            mask[model.jnt_qposadr[j]] = True
    return mask


def link_angles(model: mujoco.MjModel) -> np.ndarray:
    """[nq, nq]: each q entry as its link's angle in the world. A hinge whose parent body turns
    about a parallel hinge adds that hinge's world angle (an acrobot's elbow plus its
    shoulder); every other entry is itself. Axes are compared at the model's reference pose."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    hinge = int(mujoco.mjtJoint.mjJNT_HINGE)
    rows = np.eye(model.nq)
    for j in range(model.njnt):  # MuJoCo numbers a parent's joints before its children's
        parent = model.body_parentid[model.jnt_bodyid[j]]
        if model.jnt_type[j] != hinge or model.body_jntnum[parent] != 1:
            continue
        k = model.body_jntadr[parent]
        along = float(np.dot(data.xaxis[j], data.xaxis[k]))
        if model.jnt_type[k] == hinge and abs(abs(along) - 1.0) < 1e-6:
            rows[model.jnt_qposadr[j]] += np.sign(along) * rows[model.jnt_qposadr[k]]
    return rows


def control_range(model: mujoco.MjModel) -> np.ndarray:
    """[n_act, 2] float32 range of each actuator's control; unlimited ones: [-inf, inf]."""
    ctrl_range = np.array(model.actuator_ctrlrange, dtype=np.float32)
    ctrl_range[model.actuator_ctrllimited == 0] = [-np.inf, np.inf]
    return ctrl_range


def action_names(model: mujoco.MjModel) -> tuple[str, ...]:
    return tuple(model.actuator(a).name for a in range(model.nu))


def data_interface(xml: str, timestep: float | None = None) -> SimpleNamespace:
    """What data recorded on the system of `xml` must match (hds.data.format.validate): its
    obs_names, action_names, physics timestep and ctrl_range, from MuJoCo's compile alone
    (milliseconds, no brax), so that bad data is refused before anything is built."""
    model = load_spec(xml, timestep).compile()
    return SimpleNamespace(
        obs_names=tuple(state_names(model)),
        action_names=action_names(model),
        timestep=float(model.opt.timestep),
        ctrl_range=control_range(model),
    )


def target_names(model: mujoco.MjModel) -> dict[str, dict[str, int]]:
    """Where effects can act on this model, by target kind: {name: index}."""
    return {
        "joint": one_dof_joints(model),
        "actuator": {model.actuator(a).name: a for a in range(model.nu)},
        "body": {model.body(b).name: b - 1 for b in range(1, model.nbody)},  # brax link index
        "observation": {n: i for i, n in enumerate(state_names(model))},
    }


@pytree_dataclass
class SimState:
    pipeline: object  # the backend's state (q, qd, ...)
    effects: dict  # delay buffers and lag filters

    @property
    def q(self):
        return self.pipeline.q

    @property
    def qd(self):
        return self.pipeline.qd


@dataclass(frozen=True, eq=False)
class Simulator:
    """Pure step functions over a Brax system; hashable by identity so jit can close over it."""

    system: LazySystem  # the System (brax's, or hds.envs.mjsystem's), built on first use (`sys`)
    pipeline: object
    frames: int
    timestep: float
    effects: EffectSet
    sharpness: float | None  # smoothing of discontinuous effects; None = exact (plants)
    force_dofs: np.ndarray
    ctrl_range: np.ndarray  # [n_act, 2]
    obs_names: tuple[str, ...]
    action_names: tuple[str, ...]
    targets: dict
    angular: np.ndarray  # hinge mask over q
    link_angles: np.ndarray  # [nq, nq]: q to each link's angle in the world (`link_angles`)
    xml: str
    backend: str
    gradient_sharpness: float | None = None  # Coulomb friction's surrogate gradient, if any

    @property
    def sys(self):
        """The System (brax's; hds.envs.mjsystem's for the own backends), built on first use."""
        return self.system.sys

    def with_sys(self, sys) -> Simulator:
        """This simulator on another brax System (e.g. an edited copy of its own)."""
        return dataclasses.replace(self, system=LazySystem(None, self.backend, given=sys))

    @property
    def dt(self) -> float:
        return self.timestep * self.frames

    @property
    def n_act(self) -> int:
        return len(self.action_names)

    @property
    def nq(self) -> int:
        return len(self.angular)

    @property
    def n_obs(self) -> int:
        return len(self.obs_names)

    def init(self, q: jax.Array, qd: jax.Array, params: EffectParams = ()) -> SimState:
        """The state at (q, qd); `params` must be given when effects edit the system (mass_scale),
        since the backend's state caches quantities such as the mass matrix."""
        sys = self.effects.modify_system(params, self.sys) if params else self.sys
        return SimState(self.pipeline.init(sys, q, qd), self.effects.init_state())

    def step(self, params: EffectParams, state: SimState, u: jax.Array) -> SimState:
        sys = self.effects.modify_system(params, self.sys)
        u, est = self.effects.command(params, state.effects, u, self.sharpness)
        # Saturate before any actuator filter, as MuJoCo clamps ctrl before its dynamics.
        u = jnp.clip(u, self.ctrl_range[:, 0], self.ctrl_range[:, 1])

        def substep(carry, _):
            ps, est = carry
            applied, force, est = self.effects.substep(
                params, est, u, ps.q, ps.qd, self.timestep, self.sharpness, self.gradient_sharpness
            )
            act = jnp.concatenate([applied, force[self.force_dofs]])
            return (self.pipeline.step(sys, ps, act), est), None

        (ps, est), _ = jax.lax.scan(substep, (state.pipeline, est), None, length=self.frames)
        return SimState(ps, est)

    def observe(self, params: EffectParams, state: SimState) -> jax.Array:
        return self.effects.observe(params, jnp.concatenate([state.q, state.qd]))


def _pipeline(backend: str):
    """The backend's step functions: hds's own, or brax's pipeline (imported quietly: brax
    prints mujoco.mjx's `Failed to import warp` on import)."""
    if backend in _OWN_BACKENDS:
        return importlib.import_module(f"hds.envs.{backend}")
    with quiet_brax():
        return importlib.import_module(f"brax.{backend}.pipeline")


def brax_system(model: mujoco.MjModel):
    """brax's System of a compiled MuJoCo model (`mjcf.load_model`), kept in the program cache
    under the model's binary (hds.utils.runtime.cached_build: with every hds source file and the
    versions of brax, mujoco and jax in the key): a later process unpickles it, where
    load_model's copies into jax arrays took ~0.7 s of a second process's start. `model` is
    left as it is (load_model edits a copy)."""
    with quiet_brax():  # brax prints on import, which unpickling a System also does
        from brax.io import mjcf

    def build():
        with quiet_brax():
            return mjcf.load_model(copy.deepcopy(model))

    return cached_build("brax_system", build, model)


@dataclass(frozen=True, eq=False)
class LazySystem:
    """brax's System of `model` on `backend`, built (or unpickled from the program cache) on
    first use: a process whose programs all come from the program cache never traces the
    simulator, so it never imports brax, mujoco.mjx, trimesh and scipy.spatial (~1 s) nor
    unpickles the System (~0.3 s). hds's own backends get the fields they read, built from
    the model without brax (hds.envs.mjsystem), where the model is a tree they can simulate:
    no process of theirs imports brax. Its content, for the program cache's keys
    (hds.utils.runtime.fingerprint), is its fields: the model's binary and the backend, from
    which the System is built deterministically (brax's version is in the key), or `given`,
    a System built elsewhere (an edited copy), used as it is."""

    model: mujoco.MjModel | None  # never edited
    backend: str
    given: object = None

    @functools.cached_property  # kept beside the fields, so the content does not change
    def sys(self):
        if self.given is not None:
            return self.given
        # first used while a program is traced, as a rule: built eagerly all the same (concrete
        # arrays, as make_simulator built it before), never as the trace's values
        with jax.ensure_compile_time_eval():
            if self.backend in _OWN_BACKENDS and mjsystem.supported(self.model):
                return mjsystem.system_of(self.model)  # the fields they read, without brax
            sys = brax_system(self.model)
            if self.backend == "mjx":  # the default solver loop is a while_loop, which
                sys = sys.tree_replace({"opt.iterations": 1})  # reverse mode rejects
        return sys

    def check(self) -> None:
        """Refuse here, once, a model that hds's own backends cannot simulate (ValueError).
        The check reads the System; that it passed is kept in the program cache under the
        model and backend, so a later process does not build the System for it."""
        if self.backend not in _OWN_BACKENDS or self.given is not None:
            return
        module = importlib.import_module(f"hds.envs.{self.backend}")
        cached_build(
            "backend_check", lambda: module.check(self.sys) or True, self.model, self.backend
        )


def make_simulator(
    xml: str,
    backend: str = "generalized",
    timestep: float | None = None,
    frames: int = 1,
    effects=(),
    sharpness: float | None = 50.0,
    friction_gap: float = 1.0,
    gradient_sharpness: float | None = None,
) -> tuple[Simulator, EffectParams]:
    """Build a simulator and the parameters of its effects from an MJCF."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown brax backend '{backend}'; choose one of {list(BACKENDS)}")
    spec = load_spec(xml, timestep)
    model = spec.compile()
    targets = target_names(model)
    effect_set, params = place(effects, targets, friction_gap, model.dof_invweight0)

    for joint in targets["joint"]:  # effect forces enter as unlimited motors, on every backend
        spec.add_actuator(
            name=_FORCE_PREFIX + joint,
            target=joint,
            trntype=mujoco.mjtTrn.mjTRN_JOINT,
            ctrllimited=0,
            gear=[1, 0, 0, 0, 0, 0],
        )
    system = LazySystem(spec.compile(), backend)
    system.check()
    sim = Simulator(
        system=system,
        pipeline=_pipeline(backend),
        frames=int(frames),
        timestep=float(model.opt.timestep),
        effects=effect_set,
        sharpness=sharpness,
        force_dofs=np.array(list(targets["joint"].values()), dtype=np.int32),
        ctrl_range=control_range(model),
        obs_names=tuple(state_names(model)),
        action_names=action_names(model),
        targets=targets,
        angular=hinge_mask(model),
        link_angles=link_angles(model),
        xml=str(resolve_xml(xml)),
        backend=backend,
        gradient_sharpness=gradient_sharpness,
    )
    return sim, params
