"""Save and load fitted models with Orbax: a directory holding the parameters and normalisation
(item `state`) and a JSON description (item `meta`: kind, sizes, the system's names and dt,
the fitting config and its report). A model loads only for the system it was fitted on."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import jax
import numpy as np
import orbax.checkpoint as ocp

from hds.dynamics.model import DynamicsModel, Normalizer, init_params, n_inputs, skeleton

log = logging.getLogger(__name__)
FORMAT = "hds.dynamics/1"
HOW_TO_MAKE = (
    "fit one with `python -m hds.run method=hds dynamics=mlp` (it is saved to "
    "<run dir>/dynamics; point dynamics.path there to reuse it), or in Python with "
    "hds.dynamics.fit(...) then hds.dynamics.save(path, model, cfg, report)"
)


def _checkpointer() -> ocp.Checkpointer:
    return ocp.Checkpointer(ocp.CompositeCheckpointHandler())


def save(path, model: DynamicsModel, cfg=None, report: dict | None = None) -> Path:
    """Write `model` to the directory `path` (replaced if it exists); returns the absolute path."""
    path = Path(path).expanduser().absolute()
    meta = {
        "format": FORMAT,
        "kind": model.kind,
        "hidden": [int(w) for w in model.net.hidden],
        "members": model.members,
        "obs_names": list(model.obs_names),
        "action_names": list(model.action_names),
        "angular": [bool(a) for a in model.angular],
        "dt": float(model.dt),
        "simulator": _sim_meta(model.sim) if model.sim is not None else None,
        "config": _plain(cfg) if cfg is not None else None,
        "report": report or {},
    }
    if (
        path.exists()
        and not (path / "meta").is_dir()
        and (not path.is_dir() or any(path.iterdir()))
    ):
        raise FileExistsError(
            f"{path} exists and is not a saved dynamics model; saving would "
            "replace it: choose a new directory"
        )
    state = {"params": model.params, "norm": model.norm.as_dict()}
    path.parent.mkdir(parents=True, exist_ok=True)
    _checkpointer().save(
        path,
        args=ocp.args.Composite(state=ocp.args.StandardSave(state), meta=ocp.args.JsonSave(meta)),
        force=True,
    )
    return path


def read_meta(path) -> dict:
    """The JSON description of a saved model; FileNotFoundError naming the path when none."""
    path = Path(path).expanduser().absolute()
    if not (path / "meta").is_dir():
        what = "does not exist" if not path.exists() else "holds no saved dynamics model"
        raise FileNotFoundError(f"dynamics.path = {path} {what}: {HOW_TO_MAKE}")
    meta = _checkpointer().restore(path, args=ocp.args.Composite(meta=ocp.args.JsonRestore())).meta
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise ValueError(
            f"{path} is not a dynamics model of this version (format "
            f"{meta.get('format') if isinstance(meta, dict) else None!r}, expected "
            f"{FORMAT!r}): {HOW_TO_MAKE}"
        )
    return meta


def load(path, env) -> DynamicsModel:
    """The model saved at `path`, as an engine for `env` (its task draws the initial states and,
    for a residual model, its simulator takes the base step). Refuses a model of another system."""
    path = Path(path).expanduser().absolute()
    meta = read_meta(path)
    sim = env.sim
    problems = []
    for key, here in (("obs_names", list(sim.obs_names)), ("action_names", list(sim.action_names))):
        if meta[key] != here:
            problems.append(f"its {key} are {meta[key]}, this system's {here}")
    if not np.isclose(meta["dt"], sim.dt, rtol=1e-6):
        problems.append(f"it steps dt = {meta['dt']} s, this system {sim.dt} s")
    if problems:
        raise ValueError(
            f"the dynamics model at {path} was fitted for another system: "
            f"{'; '.join(problems)}. Fit a model for this system (dynamics.path=null "
            "fits one from the plant) or load the right one"
        )
    if meta["kind"] == "residual" and meta.get("simulator") != _sim_meta(sim):
        log.warning(
            "the residual model at %s corrects the simulator %s; it is loaded onto %s",
            path,
            meta.get("simulator"),
            _sim_meta(sim),
        )

    model = skeleton(meta["kind"], env, meta["hidden"], meta["members"])
    n_in = n_inputs(model.angular, model.n_obs, model.n_act)
    like = {
        "params": jax.eval_shape(
            lambda: init_params(model.net, jax.random.PRNGKey(0), n_in, meta["members"])
        ),
        "norm": jax.eval_shape(lambda: Normalizer.identity(n_in, model.n_obs).as_dict()),
    }
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, like)
    state = (
        _checkpointer()
        .restore(path, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract)))
        .state
    )
    return replace(model, params=state["params"], norm=Normalizer(**state["norm"]))


def _sim_meta(sim) -> dict:
    return {
        "xml": Path(sim.xml).name,
        "backend": sim.backend,
        "timestep": float(sim.timestep),
        "frames": int(sim.frames),
    }


def _plain(cfg) -> dict:
    """A config (dataclass or DictConfig) as plain JSON data."""
    from dataclasses import asdict, is_dataclass

    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)
    if is_dataclass(cfg):
        return asdict(cfg)
    return dict(cfg)
