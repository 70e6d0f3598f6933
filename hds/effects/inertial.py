"""Body effects apart from a uniform mass scale: the centre of mass further out (or in) along
the body's arm, and the rotational inertia about the centre of mass differing.

`mass_scale` multiplies a body's mass and its inertia together, which leaves a pendulum's
frequency unchanged (gravity torque m g c and pivot inertia m c^2 + I both scale); a body
measured with the centre of mass or the inertia off shows a frequency shift these two name.

Both edit the brax System (stage SYSTEM) and, in a plant, the body's explicit inertial in the
MJCF (`write_mjcf`: the compiled body mass, COM, principal frame and inertia written back as an
explicit inertial with the one quantity changed, so the law is exact whether the MJCF gives
them or the compiler infers them from geoms).
"""

from __future__ import annotations

import numpy as np

from hds.effects.base import BODY, SYSTEM, Effect, Param


def _anchor(sys, index):
    """The body's joint anchor in its own frame (brax: link.joint.pos), the point the COM is
    scaled about."""
    return sys.link.joint.pos[index]


def _compiled_inertial(spec, name: str):
    """(mass, ipos, iquat, diag inertia, joint anchor) of body `name` as MuJoCo compiles it."""
    model = spec.copy().compile()
    b = model.body(name).id
    joints = [j for j in range(model.njnt) if model.jnt_bodyid[j] == b]
    anchor = np.asarray(model.jnt_pos[joints[0]], np.float64) if joints else np.zeros(3)
    return (
        float(model.body_mass[b]),
        np.asarray(model.body_ipos[b], np.float64),
        np.asarray(model.body_iquat[b], np.float64),
        np.asarray(model.body_inertia[b], np.float64),
        anchor,
    )


def _write_inertial(spec, name, mass, ipos, iquat, inertia):
    body = spec.body(name)
    body.explicitinertial = True
    body.mass = mass
    body.ipos = ipos
    body.iquat = iquat
    body.inertia = inertia
    body.fullinertia = np.full(6, np.nan)  # the diagonal and iquat hold it


class ComScale(Effect):
    name = "com_scale"
    target_kind = BODY
    description = (
        "the body's centre of mass lies this multiple of its nominal distance from the body's "
        "joint anchor (further out above 1), along the same direction; mass and inertia about "
        "the centre of mass unchanged"
    )
    physical_name = "centre-of-mass error"
    params = (Param("scale", "1 = nominal", 1.0, lower=0.0, fit_bounds=(0.2, 5.0)),)
    stage, order = SYSTEM, 1
    mjcf = "body inertial pos (ipos)"
    mujoco_field = "MuJoCo's COM (body ipos) is a vector, not one field a scale enters"
    default_candidate = False  # opt-in: discover.effects names it

    def modify_system(self, site, p, sys):
        i, scale = site.index, p["scale"]
        inertia = sys.link.inertia
        anchor = _anchor(sys, i)
        pos = inertia.transform.pos
        pos = pos.at[i].set(anchor + scale * (pos[i] - anchor))
        inertia = inertia.replace(transform=inertia.transform.replace(pos=pos))
        sys = sys.replace(link=sys.link.replace(inertia=inertia))
        if hasattr(sys, "body_ipos"):  # the mjx backend reads MuJoCo's own fields
            sys = sys.replace(body_ipos=sys.body_ipos.at[i + 1].set(pos[i]))
        return sys

    def write_mjcf(self, spec, site, p):
        """c' = a + s (c - a), a the joint anchor, in the body's frame."""
        mass, ipos, iquat, inertia, anchor = _compiled_inertial(spec, site.target)
        _write_inertial(
            spec, site.target, mass, anchor + p["scale"] * (ipos - anchor), iquat, inertia
        )


class InertiaScale(Effect):
    name = "inertia_scale"
    target_kind = BODY
    description = (
        "the body's rotational inertia about its centre of mass is this multiple of the "
        "nominal (mass and centre of mass unchanged)"
    )
    physical_name = "inertia error"
    params = (Param("scale", "1 = nominal", 1.0, lower=0.0, fit_bounds=(0.05, 20.0)),)
    stage, order = SYSTEM, 1
    mjcf = "body inertia"
    mujoco_field = "MuJoCo's body inertia is a vector (principal moments), not one number"
    default_candidate = False  # opt-in: discover.effects names it

    def modify_system(self, site, p, sys):
        inertia = sys.link.inertia
        inertia = inertia.replace(i=inertia.i.at[site.index].multiply(p["scale"]))
        sys = sys.replace(link=sys.link.replace(inertia=inertia))
        if hasattr(sys, "body_inertia"):  # the mjx backend reads MuJoCo's own fields
            sys = sys.replace(body_inertia=sys.body_inertia.at[site.index + 1].multiply(p["scale"]))
        return sys

    def write_mjcf(self, spec, site, p):
        """I_com' = s I_com (principal axes unchanged)."""
        mass, ipos, iquat, inertia, _ = _compiled_inertial(spec, site.target)
        _write_inertial(spec, site.target, mass, ipos, iquat, p["scale"] * inertia)
