"""Identifiability before fitting: which candidate effects the data can identify at all, why
not, and what excitation would.

Pure numpy on the measured data and the MJCF (nothing compiles), so a data-collection loop
can call it after every recording to decide whether to record more:

    from hds.discover import identifiability
    for row in identifiability(dataset, env_cfg):
        if not row.identifiable:
            print(row.key, row.reason, row.excitation)

The checks are physical: an effect shows in the data only through motion it changes. A joint
that never moves (held by friction larger than any force applied) fits every friction law
alike; an actuator whose joint never moves, or whose control never varies, shows neither
its gain nor its lag; a sensor bias on a position nothing in the dynamics depends on (a
free cart on a rail, a Furuta arm turning about the vertical) is indistinguishable from where
it started. `discover` fits only the candidates that pass, and reports the others with the
excitation that would identify them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from hds.data.acquire import until_identifiable
from hds.data.format import Dataset
from hds.discover.data import noise_level
from hds.effects.base import ACTUATOR, BODY, JOINT, OBSERVATION
from hds.effects.library import default_candidates, effect_type
from hds.envs.system import load_spec, one_dof_joints, state_names

MIN_SPAN = 0.05  # share of the actuator's range the control must span to show a gain
MIN_CHANGES = 0.01  # share of steps in which the control must change to show a lag or delay
# A joint held by friction still creeps (MuJoCo's soft friction constraint, a real axis's
# pre-sliding) at speeds proportional to the force, far below what that force gives it free:
# below this share of the speed one control step of the applied force would give the free
# joint from rest, it creeps; above, it slides.
CREEP = 0.1
JOINT_TRANSMISSIONS = (int(mujoco.mjtTrn.mjTRN_JOINT), int(mujoco.mjtTrn.mjTRN_JOINTINPARENT))


@dataclass
class Identifiability:
    """Whether the data can identify one candidate effect at one place."""

    name: str
    target: str
    identifiable: bool
    reason: str  # why not (empty when identifiable)
    excitation: dict = field(default_factory=dict)  # what would: signal, amplitude, frequencies
    # not identifiable from any data of this model (e.g. a free cart's position bias), as
    # opposed to from these data (a joint the excitation never moved)
    structural: bool = False

    @property
    def key(self) -> str:
        return f"{self.name}@{self.target}"

    def to_json(self) -> dict:
        return {
            "name": self.name,
            "target": self.target,
            "identifiable": self.identifiable,
            "reason": self.reason,
            "excitation": self.excitation,
            "structural": self.structural,
        }


def moving_share(
    obs: np.ndarray, noise: np.ndarray, names, joint: str, creep: float = 0.0
) -> float | None:
    """Share of the samples in which `joint` moves: |velocity| above a tenth of its 99th
    percentile, above three times its measurement noise and above `creep` (the speed below
    which it creeps: `creep_speeds`); None without a measured velocity."""
    name = f"qd_{joint}"
    if name not in names:
        return None
    i = list(names).index(name)
    speed = np.abs(np.asarray(obs)[..., i])
    threshold = max(0.1 * float(np.percentile(speed, 99)), 3.0 * float(noise[i]), creep, 1e-9)
    return float(np.mean(speed > threshold))


def creep_speeds(model: mujoco.MjModel, actions: np.ndarray, dt: float) -> dict[str, float]:
    """{joint: speed} for each joint a motor drives: CREEP x the speed one control step (dt) of
    the motor's force (its 99th percentile in `actions`) gives the joint, free and from rest
    (the joint's inertia at qpos0, armature included). Without it, a joint friction holds
    still for a whole recording looks as if it moved: its creep is its own 99th percentile."""
    speeds = {}
    for a in range(model.nu):
        if model.actuator_biastype[a] or model.actuator_trntype[a] not in JOINT_TRANSMISSIONS:
            continue  # a servo's force is not its control times a gain
        joint = int(model.actuator_trnid[a, 0])
        gain = abs(float(model.actuator_gear[a, 0] * model.actuator_gainprm[a, 0]))
        force = gain * float(np.percentile(np.abs(actions[..., a]), 99))
        speed = CREEP * force * dt / float(model.dof_M0[model.jnt_dofadr[joint]])
        name = model.joint(joint).name
        speeds[name] = max(speeds.get(name, 0.0), speed)
    return speeds


def identifiability(
    dataset: Dataset, env_cfg, min_motion: float = 0.05, effects=None
) -> list[Identifiability]:
    """Per candidate (effect of `effects`, default the library's candidates, x place of its kind on
    the model of `env_cfg`): whether `dataset` can identify it, why not, and the excitation
    that would (within the actuators' control ranges). `min_motion`: the share of samples a
    joint must move in (discover.min_motion)."""
    model = load_spec(env_cfg.xml, env_cfg.timestep).compile()
    facts = _Facts(dataset, model, min_motion)
    rows = []
    for name in effects or default_candidates():
        kind = effect_type(name).target_kind
        for target in facts.targets[kind]:
            reason, excitation = CHECKS[kind](facts, name, target)
            structural = bool(reason) and not excitation.get("actuator")
            rows.append(Identifiability(name, target, not reason, reason, excitation, structural))
    return rows


class _Facts:
    """What the checks read: each joint's motion, each actuator's joint and control use."""

    def __init__(self, dataset: Dataset, model: mujoco.MjModel, min_motion: float):
        self.model, self.min_motion, self.dt = model, min_motion, dataset.dt
        obs = np.asarray(dataset.obs, dtype=np.float64)
        self.names = list(state_names(model))
        noise = noise_level(obs)
        self.joints = one_dof_joints(model)
        self.actions = np.asarray(dataset.actions, dtype=np.float64)
        creep = creep_speeds(model, self.actions, dataset.dt)
        self.moving = {
            j: moving_share(obs, noise, self.names, j, creep.get(j, 0.0)) for j in self.joints
        }
        self.obs = obs
        self.targets = {
            JOINT: list(self.joints),
            ACTUATOR: [model.actuator(a).name for a in range(model.nu)],
            BODY: [model.body(b).name for b in range(1, model.nbody)],
            OBSERVATION: self.names,
        }

    def still(self, joint: str) -> str:
        """Why `joint` shows nothing (it does not move), or ''."""
        share = self.moving[joint]
        if share is None or share >= self.min_motion:
            return ""
        return (
            f"{joint} moves in only {share:.1%} of the samples (at least "
            f"{self.min_motion:.0%} needed, discover.min_motion)"
        )

    def actuator(self, name: str) -> tuple[int, str]:
        a = self.model.actuator(name).id
        joint = self.model.joint(int(self.model.actuator_trnid[a, 0])).name
        return a, joint

    def limits(self, a: int) -> tuple[float, float]:
        """Actuator a's control range; an unlimited one's is what the data used."""
        if self.model.actuator_ctrllimited[a]:
            return tuple(float(x) for x in self.model.actuator_ctrlrange[a])
        u = self.actions[..., a]
        lo, hi = float(u.min()), float(u.max())
        return (lo, hi) if hi > lo else (lo - 1.0, lo + 1.0)

    def drive(self, a: int, why: str, frequencies: list[float] | None = None) -> dict:
        """The excitation of actuator a that would show an effect: its whole control range."""
        lo, hi = self.limits(a)
        gear = float(self.model.actuator_gear[a, 0])
        used = float(np.max(np.abs(self.actions[..., a] - 0.5 * (lo + hi))))
        nyquist = 0.5 / self.dt
        return {
            "actuator": self.model.actuator(a).name,
            "signal": "random steps or PRBS (hds.data.excitation)",
            "amplitude": 0.5 * (hi - lo),  # control units, around the middle of the range
            "amplitude_at_joint": 0.5 * (hi - lo) * gear,
            "used_amplitude": used,
            "frequencies_hz": frequencies or [0.0, 0.25 * nyquist],
            "why": why,
        }

    def drive_joint(self, joint: str, why: str, frequencies=None) -> dict:
        """Drive the actuator of `joint`, or (unactuated) of the joint that moves it."""
        mine = [a for a in range(self.model.nu) if self._joint_of(a) == joint]
        return self.drive(mine[0] if mine else 0, why, frequencies)

    def _joint_of(self, a: int) -> str:
        return self.model.joint(int(self.model.actuator_trnid[a, 0])).name


def _joint(facts: _Facts, name: str, target: str):
    why = facts.still(target)
    if not why:
        return "", {}
    max_force = [
        abs(float(facts.model.actuator_gear[a, 0]))
        * float(np.abs(facts.model.actuator_ctrlrange[a]).max())
        for a in range(facts.model.nu)
        if facts._joint_of(a) == target
    ]
    reason = (
        f"{why}: a joint held still fits every friction law (Coulomb friction, viscous "
        "damping) alike"
    )
    if max_force:
        reason += (
            f"; if the actuator's whole range ({max_force[0]:g} N or N m) does not move it "
            "either, the friction exceeds what the actuator can give"
        )
    slow = [0.0, 0.5 / max(10 * facts.dt, 1e-9)]  # holds of 10 steps or longer
    return reason, facts.drive_joint(
        target, f"force {target} past its friction, in both directions", slow
    )


def _actuator(facts: _Facts, name: str, target: str):
    a, joint = facts.actuator(target)
    lo, hi = facts.limits(a)
    u = facts.actions[..., a]
    why = facts.still(joint)
    if why:
        return (
            f"{why}, so the actuator {target}'s force shows in no motion",
            facts.drive(a, f"move {joint} in both directions"),
        )
    span = float(np.ptp(u)) / (hi - lo)
    needs = effect_type(name).needs
    if needs == "span" and span < MIN_SPAN:
        return (
            f"the control of {target} spans {span:.1%} of its range (at least {MIN_SPAN:.0%} "
            "needed to tell a force's size from its law)",
            facts.drive(a, "controls across the range"),
        )
    changes = float(np.mean(np.abs(np.diff(u, axis=1)) > MIN_SPAN * (hi - lo)))
    if needs == "changes" and changes < MIN_CHANGES:
        return (
            f"the control of {target} changes in {changes:.1%} of the steps (at least "
            f"{MIN_CHANGES:.0%} needed to show how fast the actuator follows)",
            facts.drive(a, "frequent control changes"),
        )
    return "", {}


def _body(facts: _Facts, name: str, target: str):
    body = facts.model.body(target).id
    joints = [
        facts.model.joint(j).name
        for j in range(facts.model.njnt)
        if facts.model.jnt_bodyid[j] == body and facts.model.joint(j).name in facts.joints
    ]
    still = [facts.still(j) for j in joints]
    if joints and all(still):
        return (
            f"{still[0]}, so the body {target}'s inertia shows in no acceleration",
            facts.drive_joint(joints[0], f"accelerate {target}"),
        )
    return "", {}


def _observation(facts: _Facts, name: str, target: str):
    kind, joint = target.split("_", 1)
    if joint not in facts.joints:
        return "", {}
    j = facts.model.joint(joint).id
    if kind == "q" and _free_of_position(facts.model, j) and not _reaches_limit(facts, j, target):
        return (
            f"nothing in the dynamics depends on where {joint} is (no spring, no gravity "
            f"{'along' if _is_slide(facts.model, j) else 'about'} it, its limits never "
            "reached): a bias of its position sensor is indistinguishable from where it "
            "started",
            {"why": f"drive {joint} into its limits, or add a reference measurement"},
        )
    why = facts.still(joint)
    if why:
        return (
            f"{why}: without an excursion of the state a bias is a constant offset no "
            "dynamics reveals",
            facts.drive_joint(joint, f"move {joint}"),
        )
    return "", {}


def _is_slide(model: mujoco.MjModel, j: int) -> bool:
    return model.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE


def _free_of_position(model: mujoco.MjModel, j: int) -> bool:
    """Whether nothing in the dynamics depends on joint j's position (its limits aside): j is
    the only joint between its body and the world, no spring holds it, and its motion is a
    symmetry of gravity: a slide across gravity (a cart on a level rail), a hinge about the
    vertical (a Furuta's arm). Below a moving joint, its position would move its body's pose
    relative to that joint, and so the inertia the joint above sees."""
    body = int(model.jnt_bodyid[j])
    if float(model.jnt_stiffness[j]) > 0 or model.body_jntnum[body] != 1:
        return False
    if _has_moving_ancestor(model, body):
        return False
    axis = _world_axis(model, body, np.asarray(model.jnt_axis[j], dtype=np.float64))
    if _is_slide(model, j):
        return not _along(axis, model.opt.gravity)
    return model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and _parallel(axis, model.opt.gravity)


def _world_axis(model: mujoco.MjModel, body: int, axis: np.ndarray) -> np.ndarray:
    """A joint's axis in the world frame at the model's reference pose."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    return data.xmat[body].reshape(3, 3) @ axis


def _has_moving_ancestor(model: mujoco.MjModel, body: int) -> bool:
    parent = int(model.body_parentid[body])
    while parent > 0:
        if model.body_jntnum[parent] > 0:
            return True
        parent = int(model.body_parentid[parent])
    return False


def _along(axis: np.ndarray, gravity) -> bool:
    """Whether gravity has a component along the axis."""
    gravity = np.asarray(gravity, dtype=np.float64)
    return bool(
        abs(axis @ gravity) > _TINY * max(np.linalg.norm(gravity) * np.linalg.norm(axis), 1e-12)
    )


def _parallel(axis: np.ndarray, gravity) -> bool:
    """Whether gravity has no component across the axis (or there is no gravity)."""
    gravity = np.asarray(gravity, dtype=np.float64)
    across = np.linalg.norm(np.cross(axis, gravity))
    return bool(across <= _TINY * max(np.linalg.norm(gravity) * np.linalg.norm(axis), 1e-12))


_TINY = 1e-6  # relative: MJCF axes are normalised, gravity is 9.81


def _reaches_limit(facts: _Facts, j: int, target: str) -> bool:
    if not facts.model.jnt_limited[j]:
        return False
    lo, hi = facts.model.jnt_range[j]
    q = facts.obs[..., facts.names.index(target)]
    margin = 0.01 * (hi - lo)
    return bool(np.any(q <= lo + margin) or np.any(q >= hi - margin))


CHECKS = {JOINT: _joint, ACTUATOR: _actuator, BODY: _body, OBSERVATION: _observation}


def unidentified(env_cfg, discover_cfg):
    """data -> what more excitation would identify in them: a reason for each candidate of
    discover_cfg.effects they cannot identify (a joint that friction holds still, an actuator
    never driven across its range; not a structural limit such as a free cart's position
    bias). The check `hds.data.acquire.until_identifiable` excites with."""

    def reasons(data):
        rows = identifiability(data, env_cfg, discover_cfg.min_motion, discover_cfg.effects)
        return [r.reason for r in rows if not r.identifiable and not r.structural]

    return reasons


def record_until_identifiable(record, env_cfg, discover_cfg, scale: float, data_so_far=()):
    """Record plant data with `record(scale, attempt) -> Dataset` (its excitation's amplitude
    `scale` of the actuators' half range); while all data so far cannot identify a candidate
    of discover_cfg.effects that more excitation would (`unidentified`), double the amplitude,
    up to the whole range, and record again (hds.data.acquire.until_identifiable). Returns
    (every dataset so far, the last amplitude, notes saying what was done and why)."""
    check = unidentified(env_cfg, discover_cfg)
    return until_identifiable(record, check, scale, data_so_far)
