"""Joint friction: Coulomb (dry) friction, viscous damping and quadratic (aerodynamic) drag."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from hds.effects.base import JOINT, SUBSTEP, SYSTEM, Effect, Param


def friction_direction(v, sharpness, gradient_sharpness=None):
    """The direction of dry friction: sign(v) when `sharpness` is None, else tanh(k v). With
    `gradient_sharpness` k_g, the value of tanh(k v) and the gradient of tanh(k_g v) (a
    surrogate gradient): a sharp law sticks like the plant's, but its gradient at rest is
    nearly zero (a small push does not move a stuck cart), which leaves a policy that starts
    inside the friction nothing to learn from; a softer law's gradient says how a larger
    push moves it."""
    if sharpness is None:
        return jnp.sign(v)
    direction = jnp.tanh(sharpness * v)
    if gradient_sharpness is None:
        return direction
    surrogate = jnp.tanh(gradient_sharpness * v)
    return surrogate + jax.lax.stop_gradient(direction - surrogate)


def stick_sharpness(force, mobility, h):
    """The sharpest tanh(k v) law an explicit step of h seconds carries stably: near rest
    F tanh(k v) is a damping F k v, and one step of it multiplies the speed by 1 - h F k w
    (w: the dof's inverse inertia), which reverses and grows it beyond k = 2 / (h F w): the
    joint then chatters about zero where the plant's sticks, and a heavy friction fits too
    weak (on the 80 N cart: 51 N at k = 50, 84 N at this cap). A softer cap (one step to
    rest, k = 1 / (h F w)) fitted worse on the same data."""
    return 2.0 / (h * mobility * jnp.maximum(force, 1e-9))


class CoulombFriction(Effect):
    name = "coulomb_friction"
    target_kind = JOINT
    description = (
        "dry friction opposing the joint's velocity with constant magnitude "
        "(smoothed as F tanh(k qd) in the differentiable simulator, k no sharper than an "
        "explicit substep carries stably; exact sign law in plants)"
    )
    physical_name = "Coulomb (dry) friction"
    params = (Param("force", "N or N m", 0.0, lower=0.0),)
    stage, order = SUBSTEP, 1
    mjcf = "joint frictionloss"
    mujoco_field = ("joint", "frictionloss", None, "add")
    friction = "force"

    def substep(self, site, p, state, u, force, q, qd, h, sharpness, gradient_sharpness):
        if sharpness is not None and site.mobility > 0:
            sharpness = jnp.minimum(sharpness, stick_sharpness(p["force"], site.mobility, h))
        direction = friction_direction(qd[site.index], sharpness, gradient_sharpness)
        return u, force.at[site.index].add(-p["force"] * direction), state

    def write_mjcf(self, spec, site, p):
        spec.joint(site.target).frictionloss += p["force"]


class ViscousDamping(Effect):
    name = "viscous_damping"
    target_kind = JOINT
    description = (
        "friction proportional to the joint's velocity (added to the joint's damping, which "
        "each backend integrates as it does the model's own: implicitly, as MuJoCo's Euler, "
        "where it can)"
    )
    physical_name = "viscous friction"
    params = (Param("coefficient", "N s/m or N m s/rad", 0.0, lower=0.0),)
    stage, order = SYSTEM, 2
    mjcf = "joint damping"
    mujoco_field = ("joint", "damping", 0, "add")
    friction = "coefficient"

    def modify_system(self, site, p, sys):
        """The joint's damping, not an explicit force: the plant's law is MuJoCo's implicit
        one, and an explicit -c qd differs from it by about h c / inertia (3% on the pole:
        fits came out 3% high, outside their intervals). The analytic, tree and MJX backends
        integrate it implicitly; brax's generalized one where the MJCF asks for an exact
        mass-matrix inverse (numeric matrix_inv_iterations 0, as the cart-pole's does)."""
        c = p["coefficient"]
        sys = sys.replace(dof=sys.dof.replace(damping=sys.dof.damping.at[site.index].add(c)))
        if hasattr(sys, "dof_damping"):  # the mjx backend reads MuJoCo's own fields
            sys = sys.replace(dof_damping=sys.dof_damping.at[site.index].add(c))
        return sys

    def write_mjcf(self, spec, site, p):
        spec.joint(site.target).damping[0] += p["coefficient"]


class QuadraticDrag(Effect):
    name = "quadratic_drag"
    target_kind = JOINT
    description = (
        "drag proportional to the square of the joint's velocity, opposing it: -c |qd| qd "
        "(air or a fluid at high Reynolds number; on a hinge, an arm's aerodynamic drag)"
    )
    physical_name = "quadratic (aerodynamic) drag"
    params = (Param("coefficient", "N s^2/m^2 or N m s^2/rad^2", 0.0, lower=0.0),)
    stage, order = SUBSTEP, 1
    friction = "coefficient"
    # opt-in: a swinging or fast body's friction law; each added default candidate costs every
    # discovery a fit per joint and changes what the existing studies measured
    default_candidate = False
    plant_stepwise = True

    # Why it is in the library: a bearing's dry friction takes the same energy per swing, so it
    # shows most when the swing is small, while an arm's air drag (each element at r moves at
    # r qd: force ~ (r qd)^2, torque ~ qd^2 times the integral of r^3 over the arm) takes most
    # when it is large. Between the two, over a range of amplitudes, the loss per swing grows
    # about as the square of the amplitude: what viscous damping alone gives. Identification data
    # that span only that range are fitted by viscous damping; its extrapolation to small (or
    # large) swings is then wrong (the real multi-arm pendulum: experiments/multiarm_pendulum).
    # On a chained arm the drag follows the arm's speed through the air, not its joint's
    # relative velocity: this law is exact on a first hinge or a slide, an approximation beyond.

    def substep(self, site, p, state, u, force, q, qd, h, sharpness, gradient_sharpness):
        v = qd[site.index]
        return u, force.at[site.index].add(-p["coefficient"] * jnp.abs(v) * v), state

    def plant_substep(self, site, p, state, loads, q, qd, h):
        """The plant's law (numpy, float64), from each physics step's starting velocity."""
        v = qd[:, site.index]
        loads.force[:, site.index] += -p["coefficient"] * np.abs(v) * v
        return state


def breakaway_magnitude(xp, force, peak, velocity, v):
    """Dry friction's magnitude at speed v with a Stribeck (breakaway) peak: at rest the
    contact's asperities have had time to bond, and breaking them takes force + peak (the
    static, breakaway level); sliding faster than the Stribeck velocity, a lubricant film
    builds up and separates them, and only the sliding (Coulomb) level is left. The peak
    decays as exp(-(v / velocity)^2) (Armstrong-Helouvry's exponent of 2, the form of the
    LuGre and Dahl models' steady state). peak = 0 is Coulomb friction."""
    return force + peak * xp.exp(-((v / velocity) ** 2))


class BreakawayFriction(Effect):
    name = "breakaway_friction"
    target_kind = JOINT
    description = (
        "dry friction with a Stribeck peak: the sliding (Coulomb) level `force` plus `peak` "
        "at rest, decaying over the Stribeck velocity, (force + peak exp(-(qd/velocity)^2)) "
        "against the motion (smoothed as Coulomb friction is in the simulator, k no sharper "
        "than a substep carries at the breakaway level; in the C MuJoCo plant MuJoCo's "
        "frictionloss set to that magnitude at every physics step, which holds a joint at "
        "rest up to force + peak); peak = 0 is coulomb_friction. An opt-in candidate that "
        "discovery tries as a refinement of a named coulomb_friction on the same joint"
    )
    physical_name = "dry friction with a Stribeck (breakaway) peak"
    params = (
        Param("force", "N or N m", 0.0, lower=0.0),
        Param("peak", "N or N m", 0.0, lower=0.0),
        # no no-op of its own (any velocity is no effect at peak 0): where a fit starts; a
        # lubricated rail or bearing's is of the order of 0.01 to 0.1 m/s (rad/s)
        Param("velocity", "m/s or rad/s", 0.1, lower=1e-6, fit_bounds=(1e-3, 10.0)),
    )
    stage, order = SUBSTEP, 1
    friction = "force"
    plant_stepwise = True
    # tried by discovery only as a refinement of a named Coulomb friction on its joint (the
    # two are nested: peak 0 is Coulomb's law), not in the default list: each added
    # candidate costs every discovery a fit per joint
    refines = ("coulomb_friction", "peak")
    default_candidate = False

    def substep(self, site, p, state, u, force, q, qd, h, sharpness, gradient_sharpness):
        v = qd[site.index]
        if sharpness is not None and site.mobility > 0:
            # the largest magnitude, at rest, sets how sharp an explicit step may make it
            breakaway = p["force"] + p["peak"]
            sharpness = jnp.minimum(sharpness, stick_sharpness(breakaway, site.mobility, h))
        direction = friction_direction(v, sharpness, gradient_sharpness)
        magnitude = breakaway_magnitude(jnp, p["force"], p["peak"], p["velocity"], v)
        return u, force.at[site.index].add(-magnitude * direction), state

    def plant_substep(self, site, p, state, loads, q, qd, h):
        """MuJoCo's frictionloss (a constraint: it holds the joint at rest up to it) set to
        the magnitude at the physics step's starting speed."""
        v = qd[:, site.index]
        magnitude = breakaway_magnitude(np, p["force"], p["peak"], p["velocity"], v)
        loads.frictionloss[:, site.index] += magnitude
        return state
