"""Hand-off to MuJoCo's own system identification, `mujoco.sysid` (the `mujoco[sysid]` extras).

Discovery's named effects become a mujoco.sysid parameter specification: `sysid/params.yaml`
(`mujoco.sysid.ParameterDict.save_to_disk`'s format) beside report.json, and `sysid/model.xml`,
the MJCF it refers to (the simulator with the named effects written as MuJoCo model fields,
each at discovery's estimate). Each parameter is one model field (the effect's
`mujoco_field`), named `<element>/<name>/<field>`, e.g. `joint/axis/frictionloss`,
`actuator/motor/biasprm[0]`: Coulomb friction is the joint's frictionloss, viscous damping its
damping, a gain the actuator's gear, an offset its affine bias, a lag its filter's dynprm[0],
a mass scale the body's mass (inertia scaled along).

Initial values are discovery's estimates, bounds the effect's own (`Param` bounds, or its
`fit_bounds`) in the field's units; mujoco.sysid's default optimizer needs finite bounds, so
an unbounded end is put ten times the effect's size away from the estimate. Effects MuJoCo has
no field for (a dead zone, an action delay counted in environment steps, a sensor bias) are
listed in the file's header, one line each, as not handed off.

`load_handoff(dir)` reads both back with a modifier on each parameter (a YAML file cannot hold
one) and `model_sequences` cuts a `Dataset` into mujoco.sysid's measured sequences, so

    spec, params = load_handoff("<discovery dir>/sysid")
    sequences = model_sequences(spec, dataset, horizon=40, stride=8)
    fitted, _ = mujoco.sysid.optimize(params, mujoco.sysid.build_residual_fn(
        models_sequences=[sequences]))
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np
from absl import logging as absl_logging

from hds.effects.apply import Site
from hds.effects.library import effect_type
from hds.utils.io import atomic_write_bytes

HANDOFF_DIR, PARAMS_FILE, MODEL_FILE = "sysid", "params.yaml", "model.xml"
UNBOUNDED_SPAN = 10.0  # an unbounded end: this many times the effect's size from the estimate


def sysid_module():
    """mujoco.sysid, checked: without the `mujoco[sysid]` extras its import succeeds empty."""
    from mujoco import sysid

    if not hasattr(sysid, "ParameterDict"):
        raise ImportError(
            "mujoco.sysid is empty: its extras are missing; install them with "
            "`pip install 'mujoco[sysid]'` (hds lists them: pip install -e .)"
        )
    return sysid


@dataclass
class Handoff:
    params: Path  # params.yaml
    model: Path  # model.xml
    handed_off: list[str] = field(default_factory=list)  # parameter names
    not_handed_off: list[str] = field(default_factory=list)  # one line each, with the reason


@dataclass(frozen=True)
class FieldParam:
    name: str  # <element>/<target>/<field>[index]
    value: float
    lower: float
    upper: float


def parameter_name(element: str, target: str, attr: str, index: int | None) -> str:
    return f"{element}/{target}/{attr}" + ("" if index is None else f"[{index}]")


def parse_name(name: str) -> tuple[str, str, str, int | None]:
    """(element, target, field, index) of `joint/axis/damping[0]`; targets may hold '/'."""
    element, rest = name.split("/", 1)
    target, attr = rest.rsplit("/", 1)
    if attr.endswith("]"):
        attr, index = attr[:-1].split("[")
        return element, target, attr, int(index)
    return element, target, attr, None


def get_field(spec: mujoco.MjSpec, element: str, target: str, attr: str, index: int | None):
    if (element, attr) == ("body", "mass"):  # the geoms may give it: the compiled mass
        return float(spec.compile().body(target).mass[0])
    value = getattr(getattr(spec, element)(target), attr)
    return float(value if index is None else value[index])


def set_field(spec, element: str, target: str, attr: str, index: int | None, value: float):
    obj = getattr(spec, element)(target)
    if index is None:
        setattr(obj, attr, value)
    else:
        getattr(obj, attr)[index] = value


def _finite_bounds(value: float, size: float, lower: float, upper: float) -> tuple[float, float]:
    span = UNBOUNDED_SPAN * max(abs(size), 1e-9)
    return (
        lower if math.isfinite(lower) else value - span,
        upper if math.isfinite(upper) else value + span,
    )


def field_param(base: mujoco.MjSpec, spec: mujoco.MjSpec, effect) -> FieldParam | str:
    """The effect (a NamedEffect) as a model field of `spec`, which holds it already (but for
    the offset, written here as the actuator's affine bias), `base` the spec without it; or
    why it cannot be one."""
    kind = effect_type(effect.name)
    if isinstance(kind.mujoco_field, str):
        return kind.mujoco_field
    element, attr, index, law = kind.mujoco_field
    (param,) = kind.params
    lower, upper = param.fit_bounds or (param.lower, param.upper)
    where = (element, effect.target, attr, index)
    if law == "bias":  # force = gain (u + offset): the bias is gain x offset
        actuator = spec.actuator(effect.target)
        if actuator.biastype != mujoco.mjtBias.mjBIAS_NONE or actuator.ctrllimited == 1:
            return (
                "the actuator has a bias or a limited control: MuJoCo's bias acts after the "
                "saturation, hds's offset before"
            )
        gain = float(actuator.gainprm[0])
        actuator.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        set_field(spec, *where, gain * float(effect.params[param.name]))
        lower, upper = sorted((gain * lower, gain * upper))
        origin = 0.0
    else:
        origin = get_field(base, *where)
    value = get_field(spec, *where)
    if law == "scale":  # field = origin x parameter
        lower, upper = origin * lower, origin * upper
    else:  # field = origin + parameter
        lower, upper = origin + lower, origin + upper
    lower, upper = _finite_bounds(value, value - origin, lower, upper)
    return FieldParam(parameter_name(*where), value, lower, upper)


def write_handoff(env_cfg, named, out_dir) -> Handoff:
    """out_dir/sysid/{params.yaml, model.xml}: discovery's named effects (`NamedEffect`s, e.g.
    `Discovery.missing_effects`) on the simulator of `env_cfg` as a mujoco.sysid parameter
    specification and the MJCF it refers to (both written atomically)."""
    from hds.real.mujoco_plant import mujoco_spec

    sysid = sysid_module()
    folder = Path(out_dir) / HANDOFF_DIR
    base = mujoco_spec(env_cfg, list(env_cfg.effects))
    spec = mujoco_spec(env_cfg, [*env_cfg.effects, *(e.as_effect() for e in named)])
    params, skipped = sysid.ParameterDict(), []
    for effect in named:
        found = field_param(base, spec, effect)
        if isinstance(found, str):
            skipped.append(f"{effect.name}@{effect.target} {dict(effect.params)}: {found}")
        else:
            params.add(sysid.Parameter(found.name, found.value, found.lower, found.upper))
    handoff = Handoff(folder / PARAMS_FILE, folder / MODEL_FILE, list(params.keys()), skipped)
    header = [
        "# mujoco.sysid parameter specification written by hds.discover "
        "(ParameterDict.load_from_disk reads it).",
        f"# Model: {MODEL_FILE} (the simulator, each named effect MuJoCo has at its estimate).",
        "# Names are <element>/<name>/<field>[index] of that MJCF; "
        "hds.discover.sysid.load_handoff attaches the modifiers.",
        "# Not handed off: " + ("none" if not skipped else ""),
        *[f"#   {line}" for line in skipped],
    ]
    with tempfile.TemporaryDirectory() as tmp:
        params.save_to_disk(Path(tmp) / PARAMS_FILE)
        body = (Path(tmp) / PARAMS_FILE).read_bytes()
    atomic_write_bytes(handoff.model, spec.to_xml().encode())
    atomic_write_bytes(handoff.params, ("\n".join(header) + "\n").encode() + body)
    return handoff


def set_mass(spec: mujoco.MjSpec, body: str, mass: float) -> None:
    """The body's mass, its inertia scaled along: hds's mass_scale law (through the geoms where
    the compiler infers inertia from them). mujoco.sysid's own mass modifier fails in 3.17."""
    scale = mass / get_field(spec, "body", body, "mass", None)
    site = Site("mass_scale", body, -1)
    effect_type("mass_scale").write_mjcf(spec, site, {"scale": scale})


def modifier(name: str):
    """The modifier writing a parameter named `<element>/<name>/<field>[index]` into a spec."""
    element, target, attr, index = parse_name(name)
    if (element, attr) == ("body", "mass"):
        return lambda spec, p: set_mass(spec, target, float(p.value[0]))
    return lambda spec, p: set_field(spec, element, target, attr, index, float(p.value[0]))


def load_handoff(folder) -> tuple[mujoco.MjSpec, object]:
    """(the MjSpec of model.xml, the mujoco.sysid ParameterDict of params.yaml with modifiers)."""
    sysid = sysid_module()
    folder = Path(folder)
    params = sysid.ParameterDict.load_from_disk(folder / PARAMS_FILE)
    spec = mujoco.MjSpec.from_file(str(folder / MODEL_FILE))
    for name, param in params.items():
        element, target, attr, index = parse_name(name)
        if element not in ("joint", "actuator", "body") or getattr(spec, element)(target) is None:
            raise ValueError(
                f"{folder / PARAMS_FILE}: parameter {name!r} names no {element} of "
                f"{MODEL_FILE}; names are <joint|actuator|body>/<name>/<field>[index]"
            )
        param.modifier = modifier(name)
    return spec, params


def model_sequences(spec: mujoco.MjSpec, dataset, horizon: int, stride: int, episodes=None):
    """mujoco.sysid.ModelSequences of a Dataset: windows of `horizon` steps every `stride` steps
    of the given episodes (all by default), each from its measured state; the controls held
    over each step (repeated at every physics timestep), the joints' qpos and qvel measured."""
    sysid = sysid_module()
    model = spec.compile()
    frames = round(dataset.dt / model.opt.timestep)
    joints = [model.joint(j).name for j in range(model.njnt)]
    if model.nq != model.njnt or model.nv != model.njnt or dataset.n_obs != 2 * model.njnt:
        raise ValueError(
            "model_sequences needs one slide or hinge joint per observed q and qd "
            f"(the model has nq = {model.nq}, nv = {model.nv}; the data {dataset.n_obs} signals)"
        )
    names = [f"{j}_qpos" for j in joints] + [f"{j}_qvel" for j in joints]
    episodes = range(dataset.n_episodes) if episodes is None else episodes
    windows = [(e, t) for e in episodes for t in range(0, dataset.horizon - horizon + 1, stride)]
    control_times = np.arange(horizon * frames) * model.opt.timestep
    obs_times = np.arange(horizon + 1) * dataset.dt
    initial, controls, measured = [], [], []
    for e, t in windows:
        obs = dataset.obs[e, t : t + horizon + 1]
        u = np.repeat(dataset.actions[e, t : t + horizon], frames, axis=0)
        initial.append(sysid.create_initial_state(model, obs[0, : model.nq], obs[0, model.nq :]))
        controls.append(sysid.TimeSeries.from_control_names(control_times, u, model))
        measured.append(sysid.TimeSeries.from_names(obs_times, obs, model, names))
    labels = [f"episode{e}_step{t}" for e, t in windows]
    # The measured signals are states, not sensors: allowed, but logged once per window.
    verbosity = absl_logging.get_verbosity()
    absl_logging.set_verbosity(absl_logging.ERROR)
    try:
        return sysid.ModelSequences(
            spec.modelname or "model", spec, labels, initial, controls, measured, True
        )
    finally:
        absl_logging.set_verbosity(verbosity)
