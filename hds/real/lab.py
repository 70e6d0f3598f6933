"""Lab plants: seeded draws of a robot that differs from its model in many ways at once.

`real=lab_cartpole` and `real=lab_furuta` are families; `real.draw=K` picks one member. A
draw is a plain dict (`draw(family, k)`, the draw's truth): every parameter drawn from the
family's documented distribution (`FAMILIES`, docs/lab-plants.md) and the effects the plant
hides with those values, which `RealConfig` puts into `real.effects`. The C MuJoCo plant then
applies their exact laws and the oracle (`simulator=real`) trains on their replicas. A run on
a lab plant writes the truth to `<run dir>/truth.json`.

Every draw has: each mass, the centre of mass and the inertia of each link that turns, and
the motor's gear or torque constant off by up to 10%; friction on every joint (Coulomb with a static
Stribeck peak, plus viscous); 0 or 1 step of delay, an amplifier dead band and its
saturation; noise on the measured velocities and 2,048-count encoders on the positions; and
effects outside discovery's library: backlash in the cart-pole's belt drive and a rough patch
of its rail, cogging of the Furuta's motor (`hds.effects.lab`).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np

from hds.effects.apply import applied
from hds.effects.library import candidate_effects

COUNTS = 2048  # encoder counts a turn


@dataclass(frozen=True)
class Draw:
    """One drawn parameter: effect@target.param ~ uniform [low, high], or a uniform choice of
    `choices`; with `times`, the value is that other parameter of the same effect times the
    draw (a static friction above the sliding one); `value`: fixed."""

    effect: str
    target: str
    param: str
    low: float = 0.0
    high: float = 0.0
    choices: tuple = ()
    times: str = ""
    value: float | None = None

    @property
    def key(self) -> str:
        return f"{self.effect}@{self.target}.{self.param}"

    def bounds(self, values: dict) -> tuple[float, float]:
        """The documented range of the value (given the draws it depends on)."""
        if self.value is not None:
            return self.value, self.value
        if self.choices:
            return min(self.choices), max(self.choices)
        scale = values[f"{self.effect}@{self.target}.{self.times}"] if self.times else 1.0
        return self.low * scale, self.high * scale


def _stribeck(joint, force, ratio, velocity, viscous):
    return (
        Draw("stribeck_friction", joint, "force", *force),
        Draw("stribeck_friction", joint, "static", *ratio, times="force"),
        Draw("stribeck_friction", joint, "velocity", *velocity),
        Draw("viscous_damping", joint, "coefficient", *viscous),
    )


def _scales(*places, low=0.9, high=1.1):
    return tuple(Draw(effect, target, "scale", low, high) for effect, target in places)


TURN = 2 * math.pi / COUNTS

# The cart-pole (cartpole.xml: a 10.5 kg cart on a rail, a 5 kg, 0.6 m pole, a 100 N motor gear
# and controls of +-3): a belt-driven cart, as a lab's linear cart is.
CARTPOLE = (
    *_scales(("mass_scale", "cart"), ("mass_scale", "pole")),
    *_scales(("com_scale", "pole"), ("inertia_scale", "pole")),
    Draw("actuator_gain", "slide", "gain", 0.9, 1.1),
    *_stribeck("slider", (5.0, 15.0), (1.2, 1.6), (0.02, 0.1), (0.2, 2.0)),
    *_stribeck("hinge", (0.05, 0.3), (1.2, 1.6), (0.05, 0.2), (0.02, 0.2)),
    Draw("action_delay", "slide", "steps", choices=(0, 1)),
    Draw("actuator_deadzone", "slide", "width", 0.01, 0.04),
    Draw("actuator_saturation", "slide", "limit", 2.7, 3.0),
    # the belt's play (m) and the motor side's mass over the gear (0.5-1 kg)
    Draw("backlash", "slide", "gap", 0.002, 0.006),
    Draw("backlash", "slide", "inertia", 0.005, 0.01),
    Draw("sensor_noise", "qd_slider", "std", 0.005, 0.02),
    Draw("sensor_noise", "qd_hinge", "std", 0.01, 0.04),
    # a 2,048-count encoder on a 10 mm belt pulley, and on the hinge
    Draw("encoder_quantization", "q_slider", "step", value=0.01 * TURN),
    Draw("encoder_quantization", "q_hinge", "step", value=TURN),
    # a rough patch of the rail where the cart runs (last: the draws above keep their values)
    Draw("patch_friction", "slider", "force", 2.0, 8.0),
    Draw("patch_friction", "slider", "center", -0.3, 0.3),
    Draw("patch_friction", "slider", "width", 0.05, 0.15),
)

# The Furuta pendulum (furuta.xml: the QUBE-Servo 2, motor torque 0.005 N m/V, +-5 V): a
# direct drive with a cogging motor.
FURUTA = (
    *_scales(("mass_scale", "arm"), ("mass_scale", "pendulum")),
    *_scales(("com_scale", "arm"), ("inertia_scale", "arm")),
    *_scales(("com_scale", "pendulum"), ("inertia_scale", "pendulum")),
    Draw("actuator_gain", "motor", "gain", 0.9, 1.1),
    *_stribeck("arm", (2e-4, 8e-4), (1.2, 1.6), (0.05, 0.3), (2e-6, 2e-5)),
    *_stribeck("pendulum", (5e-6, 3e-5), (1.2, 1.6), (0.05, 0.3), (5e-7, 5e-6)),
    Draw("action_delay", "motor", "steps", choices=(0, 1)),
    Draw("actuator_deadzone", "motor", "width", 0.05, 0.2),
    Draw("actuator_saturation", "motor", "limit", 4.5, 5.0),
    # 1-3% of the motor's 0.025 N m, 12 to 24 periods a turn
    Draw("cogging_torque", "arm", "amplitude", 2.5e-4, 7.5e-4),
    Draw("cogging_torque", "arm", "periods", choices=tuple(range(12, 25))),
    Draw("cogging_torque", "arm", "phase", 0.0, 2 * math.pi),
    Draw("sensor_noise", "qd_arm", "std", 0.01, 0.05),
    Draw("sensor_noise", "qd_pendulum", "std", 0.01, 0.05),
    Draw("encoder_quantization", "q_arm", "step", value=TURN),
    Draw("encoder_quantization", "q_pendulum", "step", value=TURN),
)

FAMILIES: dict[str, tuple[str, tuple[Draw, ...]]] = {
    "lab_cartpole": ("cartpole.xml", CARTPOLE),
    "lab_furuta": ("furuta.xml", FURUTA),
}
SEED_EFFECTS = ("sensor_noise",)  # their `seed` is the draw's


def _family(family: str):
    if family not in FAMILIES:
        raise ValueError(
            f"real.family = {family!r} is no lab family; choose one of {list(FAMILIES)}"
        )
    return FAMILIES[family]


def draw(family: str, k: int) -> dict:
    """The truth of draw k of a family: {family, draw, xml, values {effect@target.param:
    value}, effects [{name, target, params}] (every parameter, as a plant applies it),
    out_of_library [effect@target that discovery has no candidate for]}. The same (family, k)
    gives the same dict on every machine (numpy's PCG64 seeded by both)."""
    xml, table = _family(family)
    if isinstance(k, bool) or not isinstance(k, int) or k < 0:
        raise ValueError(f"real.draw = {k!r} must be a whole number >= 0")
    rng = np.random.default_rng([k, zlib.crc32(family.encode())])
    values: dict[str, float] = {}
    for d in table:
        if d.value is not None:
            values[d.key] = float(d.value)
        elif d.choices:
            values[d.key] = d.choices[int(rng.integers(len(d.choices)))]
        else:
            low, high = d.bounds(values)
            values[d.key] = float(rng.uniform(low, high))
    effects: dict[tuple[str, str], dict] = {}
    for d in table:
        effects.setdefault((d.effect, d.target), {})[d.param] = values[d.key]
    for (name, _), params in effects.items():
        if name in SEED_EFFECTS:
            params["seed"] = k
    specs = applied([{"name": n, "target": t, "params": p} for (n, t), p in effects.items()])
    library = set(candidate_effects())
    return {
        "family": family,
        "draw": k,
        "xml": xml,
        "values": values,
        "effects": specs,
        "out_of_library": [f"{e['name']}@{e['target']}" for e in specs if e["name"] not in library],
    }


def effects(family: str, k: int) -> list[dict]:
    """The effects draw k of a family hides (what `real.effects` holds for it)."""
    return draw(family, k)["effects"]


def check_env(family: str, xml: str) -> None:
    """Refuse a lab family on another system's model, naming the envs it fits."""
    own, _ = _family(family)
    if xml.rsplit("/", 1)[-1] != own:
        envs = {"cartpole.xml": "cartpole_balance", "furuta.xml": "furuta_balance"}[own]
        raise ValueError(
            f"real.family = {family} is a plant of {own}, and env.xml is {xml}; choose an env "
            f"on {own} (env={envs} or its swing-up)"
        )


def in_bounds(family: str, truth: dict) -> list[str]:
    """The values of a truth dict outside the family's documented ranges (none for a draw)."""
    _, table = _family(family)
    values = truth["values"]
    out = []
    for d in table:
        low, high = d.bounds(values)
        value = values[d.key]
        if d.choices and value not in d.choices or not low <= value <= high:
            out.append(f"{d.key} = {value} outside [{low}, {high}]")
    return out


# effects on the observations (no dynamics for a simulator to be randomized over)
OBSERVED = ("sensor_noise", "encoder_quantization")


def randomization(family: str) -> list[dict]:
    """Domain randomization over the family's own distribution (`dr.effects`: [{name, target,
    ranges: {param: [low, high]}}]): every drawn value's whole range, a static friction's from
    the lowest sliding force times the lowest ratio to the highest times the highest. Left
    out, as a randomized simulator cannot draw them per rollout: discrete values (the delay's
    steps, the cogging's periods: an effect whose period is not drawn is dropped, as a cogging
    of the wrong period is another disturbance) and the effects on the observations."""
    _, table = _family(family)
    low: dict[str, float] = {}
    high: dict[str, float] = {}
    for d in table:
        low[d.key], high[d.key] = d.bounds(low)[0], d.bounds(high)[1]
    dropped = {(d.effect, d.target) for d in table if d.choices or d.effect in OBSERVED}
    ranged: dict[tuple[str, str], dict] = {}
    for d in table:
        if (d.effect, d.target) not in dropped:
            ranged.setdefault((d.effect, d.target), {})[d.param] = [low[d.key], high[d.key]]
    return [{"name": n, "target": t, "ranges": r} for (n, t), r in ranged.items()]
