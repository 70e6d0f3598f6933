"""What an effect is: one object that owns everything about one physical effect.

An effect is a subclass of `Effect` whose class attributes say what it is (name, the kind
of target it acts on, its parameters with units, bounds and the nominal value at which it
does nothing, its physical name, whether MuJoCo has it natively) and whose methods are its
laws: the differentiable one (jax, on the simulator's step, at the effect's `stage`) and the
exact one of the C MuJoCo plant (numpy, float64: written into the plant's MJCF, or applied
in the plant's step). `hds.effects.library.register` puts an instance in the library.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

JOINT, ACTUATOR, BODY, OBSERVATION = "joint", "actuator", "body", "observation"
TARGET_KINDS = (JOINT, ACTUATOR, BODY, OBSERVATION)

# Where in a simulator step an effect acts, in this order:
SYSTEM = "system"  # edits the brax System (its differentiable law: `modify_system`)
COMMAND = "command"  # on the control, once per environment step (`command`)
SUBSTEP = "substep"  # every physics substep: filter states, joint forces (`substep`)
OBSERVE = "observe"  # on the observation (`observe`)
STAGES = (SYSTEM, COMMAND, SUBSTEP, OBSERVE)


@dataclass(frozen=True)
class Param:
    name: str
    unit: str
    nominal: float  # the value at which the effect does nothing
    lower: float = -math.inf
    upper: float = math.inf
    discrete: bool = False  # integer, fitted by enumeration rather than by gradient
    # gap discovery: tighter bounds where the physics degenerates (a massless body), and a
    # start of this many simulator timesteps above nominal where nominal has no gradient
    fit_bounds: tuple[float, float] | None = None
    fit_start_in_timesteps: float = 0.0


@dataclass
class PlantLoads:
    """What the C MuJoCo plant holds over one physics step of its B episodes, edited by the
    stepwise plant laws (`Effect.plant_substep`): the actuators' controls [B, nu], the forces
    on the dofs [B, nv] (qfrc_applied) and each dof's dry-friction magnitude [B, nv] (MuJoCo's
    frictionloss, a constraint that holds a joint at rest up to it)."""

    ctrl: object
    force: object
    frictionloss: object


class Effect:
    """Base class of the library's effects: set the class attributes, write the laws of its
    stage (jax) and of the plant (numpy, or `mjcf` and `write_mjcf`), then register an
    instance. `site` (hds.effects.apply.Site) says where it acts: `site.index` is the dof
    of a joint, the actuator's index, the brax link of a body (body id - 1) or the index of
    an observation; `p` is the site's {param: value} dict."""

    name: str
    target_kind: str  # JOINT, ACTUATOR, BODY or OBSERVATION
    description: str
    physical_name: str  # how discovery's reports name it
    params: tuple[Param, ...]
    stage: str  # SYSTEM, COMMAND, SUBSTEP or OBSERVE
    order: int = 0  # a stage applies its effects in increasing order (then as placed)
    mjcf: str = ""  # what it is in an MJCF when MuJoCo has it natively ('' when it has not)
    # the MuJoCo model field its one parameter is, for the mujoco.sysid hand-off
    # (hds.discover.sysid): (element, field, index or None, how the parameter enters it: 'add',
    # 'scale' or 'bias', the actuator's affine bias), or why it has none
    mujoco_field: tuple | str = "MuJoCo has no field for it"
    friction: str = ""  # the parameter `real.friction_gap` scales ('' : not a friction)
    # what identifiability asks of an actuator's control for this effect: 'span' (a force's
    # size shows across the range) or 'changes' (how fast the actuator follows shows in them)
    needs: str = ""
    # discovery fits it by shifting the measured actions (a delay): its one discrete
    # parameter is enumerated, with no parameter in the simulator
    shifts_actions: bool = False
    # one of discovery's candidates; False: a generic effect it fits otherwise (force terms)
    candidate: bool = True
    # in discover.effects' default list; False: a candidate a user names (each added candidate
    # costs every discovery a fit per place, and changes what the existing studies measured)
    default_candidate: bool = True
    # (effect, parameter): the candidate on the same target whose law this one's holds as a
    # special case, and this one's parameter whose nominal value makes it that law (a
    # Stribeck peak of 0 is Coulomb friction); discovery tries it only in that one's place
    # once that one is named (`hds.discover.explain._refine`), never on its own
    refines: tuple[str, str] | tuple = ()
    # its C MuJoCo law acts at every physics step on the episodes' state (`plant_substep`)
    # rather than as a constant force (`plant_force`): friction that varies with speed, a
    # torque that varies with angle, a drive with a state of its own
    plant_stepwise: bool = False

    def check_site(self, target: str, values: dict, names: dict, where: str) -> None:
        """Refuse, with one line, what its parameters cannot mean on this model; `names`: the
        model's targets by kind (hds.effects.apply.check)."""

    def param(self, name: str) -> Param:
        return next(p for p in self.params if p.name == name)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"

    # -- the differentiable law (jax), called by hds.effects.apply.EffectSet ----------------
    def init_state(self, site):
        """The state a stateful effect carries (a filter, a buffer); None: stateless."""
        return None

    def modify_system(self, site, p, sys):
        raise self._missing("modify_system")

    def command(self, site, p, state, u, sharpness):
        """(control, state) after the effect; `sharpness`: None for the exact law, else the
        smoothing of a discontinuous law."""
        raise self._missing("command")

    def substep(self, site, p, state, u, force, q, qd, h, sharpness, gradient_sharpness):
        """(applied control, joint forces [nqd], state) after the effect, for one substep
        of h seconds at joint positions q and velocities qd."""
        raise self._missing("substep")

    def observe(self, site, p, obs):
        raise self._missing("observe")

    # -- the exact law of the C MuJoCo plant (numpy, float64), hds.real.MujocoPlant ---------
    def write_mjcf(self, spec, site, p) -> None:
        """Write the effect into the plant's mujoco.MjSpec (effects with `mjcf`)."""
        raise self._missing("write_mjcf")

    def plant_state(self, site, episodes: int):
        return None

    def plant_command(self, site, p, state, u):
        """(control [B, n_act], state) after the effect; u may be edited in place."""
        raise self._missing("plant_command")

    def plant_force(self, site, p) -> float:
        """A substep effect MuJoCo lacks: the constant force on the joint's dof the plant
        applies (qfrc_applied)."""
        raise self._missing("plant_force")

    def plant_substep(self, site, p, state, loads, q, qd, h):
        """A stepwise plant law (`plant_stepwise`): edit `loads` (PlantLoads) for one physics
        step of h seconds from the episodes' positions q [B, nq] and velocities qd [B, nv] at
        its start; return the effect's next state (`plant_state`)."""
        raise self._missing("plant_substep")

    def plant_observe(self, site, p, obs):
        """Observations [B, n_obs] after the effect; obs may be edited in place. An effect
        whose `plant_state` is not None (a noise generator) is called with it as a fourth
        argument; that state lives as long as the plant (it is not reset with the episodes)."""
        raise self._missing("plant_observe")

    def _missing(self, law: str) -> NotImplementedError:
        return NotImplementedError(
            f"effect '{self.name}' (stage {self.stage}) has no {law}; define it in its class"
        )
