"""A generic joint force beyond the named effects: a sum of coefficient x feature terms.

`FEATURES` is the one vocabulary of terms: the effect's parameters are their coefficients, and
gap discovery's sparse regression (hds.discover.terms) selects among the same features, so
what it fits is added to the corrected simulator as `joint_force_terms` as it is. sign(qd) is
exact in discovery's regression and in the brax plant, and smoothed as the friction effects'
is (hds.effects.friction.friction_direction) in the differentiable simulator. u is the control
the actuator applies (after the command effects and the lag); discovery regresses on the
measured action, the same thing unless a named actuator effect transforms it. The position is
read at the joint's dof index, which `check_site` makes sure is its position's index too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import jax.numpy as jnp

from hds.effects.base import JOINT, SUBSTEP, Effect, Param
from hds.effects.friction import friction_direction

SLIDE, HINGE = "slide", "hinge"


@dataclass(frozen=True)
class Feature:
    param: str  # the effect's parameter: this term's coefficient
    label: str  # how reports write the term
    unit: str  # of the coefficient; {F}: N or N m, {Q}: m or rad (slide or hinge)
    reading: str  # what a force of coefficient x term is physically
    value: Callable  # (array module, q, qd, sign(qd), control) -> the term
    joints: tuple[str, ...] = (SLIDE, HINGE)  # where discovery offers it
    # (effect, parameter) of the library whose force on a joint is -parameter x this term
    same_law: tuple[str, str] | None = None

    def unit_on(self, joint: str) -> str:
        return self.unit.format(**UNITS[joint])


UNITS = {SLIDE: {"F": "N", "Q": "m"}, HINGE: {"F": "N m", "Q": "rad"}}

FEATURES = (
    # on a hinge, the unwrapped angle as the plant integrates it (a torsional spring -k q):
    # discovery offers it there only where the record does not wrap the angle
    # (hds.discover.terms.angle_reading)
    Feature(
        "q",
        "q",
        "{F}/{Q}",
        "a spring (stiffness k = -coefficient)",
        lambda xp, q, qd, s, u: q,
    ),
    Feature(
        "sin_q",
        "sin q",
        "{F}",
        "a torque in sin of the angle (gravity-like)",
        lambda xp, q, qd, s, u: xp.sin(q),
        (HINGE,),
    ),
    Feature(
        "cos_q",
        "cos q",
        "{F}",
        "a torque in cos of the angle (an offset gravity)",
        lambda xp, q, qd, s, u: xp.cos(q),
        (HINGE,),
    ),
    Feature(
        "qd",
        "qd",
        "{F} s/{Q}",
        "viscous friction (coefficient = -coefficient)",
        lambda xp, q, qd, s, u: qd,
        same_law=("viscous_damping", "coefficient"),
    ),
    Feature(
        "sign_qd",
        "sign(qd)",
        "{F}",
        "dry (Coulomb) friction (force = -coefficient)",
        lambda xp, q, qd, s, u: s,
        same_law=("coulomb_friction", "force"),
    ),
    Feature(
        "abs_qd_qd",
        "|qd| qd",
        "{F} s^2/{Q}^2",
        "quadratic drag (coefficient = -coefficient)",
        lambda xp, q, qd, s, u: xp.abs(qd) * qd,
        same_law=("quadratic_drag", "coefficient"),
    ),
    Feature(
        "u",
        "u",
        "{F} per control unit",
        "a force proportional to the control",
        lambda xp, q, qd, s, u: u,
    ),
)
FEATURE = {f.param: f for f in FEATURES}


def term_force(xp, coefficients: dict, q, qd, sign_qd, u):
    """The sum of coefficient x feature over the features in `coefficients`."""
    return sum(c * FEATURE[name].value(xp, q, qd, sign_qd, u) for name, c in coefficients.items())


class JointForceTerms(Effect):
    name = "joint_force_terms"
    target_kind = JOINT
    description = (
        "a force on the joint that is a sum of coefficient x term of its position, velocity and "
        "a control: " + ", ".join(f.label for f in FEATURES)
    )
    physical_name = "joint force terms beyond the library"
    params = tuple(
        Param(f.param, f"{f.unit_on(SLIDE)} or {f.unit_on(HINGE)}", 0.0) for f in FEATURES
    ) + (Param("actuator", "index of the actuator whose control u is", 0, lower=0, discrete=True),)
    stage, order = SUBSTEP, 3  # after the actuator lag: u is the control the actuator applies
    candidate = False  # fitted by hds.discover.terms, not as one of discovery's candidates

    def check_site(self, target, values, names, where):
        actuators = list(names["actuator"])
        if values["actuator"] >= len(actuators):
            raise ValueError(
                f"{where}: actuator = {values['actuator']} is no actuator of this model; "
                f"give the index of one of {actuators}"
            )
        # the law reads the joint's position at its dof's index (hds.effects.apply.Site)
        if names["observation"][f"q_{target}"] != names["joint"][target]:
            raise ValueError(
                f"{where}: the joint's position and velocity have different indices (a free "
                "or ball joint comes first); put the one-dof joints first in the MJCF"
            )

    def substep(self, site, p, state, u, force, q, qd, h, sharpness, gradient_sharpness):
        j = site.index
        sign_qd = friction_direction(qd[j], sharpness, gradient_sharpness)
        control = u[site.static("actuator")]
        return u, force.at[j].add(term_force(jnp, p, q[j], qd[j], sign_qd, control)), state

    def plant_force(self, site, p):
        raise ValueError(
            f"{self.name}@{site.target}: the C MuJoCo plant holds only constant joint forces; "
            "hide a spring or damper in the MJCF (joint stiffness, damping), or use real=brax"
        )
