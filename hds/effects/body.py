"""Body effects: mass (and inertia) error."""

from __future__ import annotations

import math

import mujoco
import numpy as np

from hds.effects.base import BODY, SYSTEM, Effect, Param


class MassScale(Effect):
    name = "mass_scale"
    target_kind = BODY
    description = "the body's mass, and with it its inertia, is this multiple of the nominal"
    physical_name = "mass error"
    params = (Param("scale", "1 = nominal", 1.0, lower=0.0, fit_bounds=(0.05, 20.0)),)
    stage, order = SYSTEM, 0
    mjcf = "body mass and inertia"
    mujoco_field = ("body", "mass", None, "scale")

    def modify_system(self, site, p, sys):
        scale = p["scale"]
        inertia = sys.link.inertia
        inertia = inertia.replace(
            mass=inertia.mass.at[site.index].multiply(scale),
            i=inertia.i.at[site.index].multiply(scale),
        )
        sys = sys.replace(link=sys.link.replace(inertia=inertia))
        if hasattr(sys, "body_mass"):  # the mjx backend reads MuJoCo's own fields
            sys = sys.replace(
                body_mass=sys.body_mass.at[site.index + 1].multiply(scale),
                body_inertia=sys.body_inertia.at[site.index + 1].multiply(scale),
            )
        return sys

    def write_mjcf(self, spec, site, p):
        """Scale the body's mass and inertia: through its geoms when the compiler infers them."""
        body, scale = spec.body(site.target), p["scale"]
        mode = spec.compiler.inertiafromgeom
        from_geoms = mode == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE or (
            mode == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_AUTO and not body.explicitinertial
        )
        if from_geoms:  # mass and inertia are linear in density (or in a geom's given mass)
            for geom in body.geoms:
                geom.density *= scale
                if not math.isnan(geom.mass):
                    geom.mass *= scale
        else:
            body.mass *= scale
            body.inertia = np.asarray(body.inertia) * scale
            body.fullinertia = np.asarray(body.fullinertia) * scale  # NaN (unused) stays NaN
