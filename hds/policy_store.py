"""A trained batch of policies as its own artefact: the network's spec and every run's
parameters, written when training ends, so loading a policy needs no trainer.

    <run dir>/policies/<method>/policy.json   spec: the network (hidden widths, which
                                              observations are hinge angles, control range,
                                              activation), the layers' array names, each
                                              run's seed and settings and epoch
    <run dir>/policies/<method>/policy.npz    Dense_<i>_kernel [n_runs, in, out], Dense_<i>_bias
                                              [n_runs, out]; low, high, angular (the module's
                                              own arrays, exact)

The layers are named as `hds.export` names them; the parameters are the run's returned policy
(the last iterate, or the kept best: algo.keep). A run directory written before this artefact
existed is read from its last checkpoint instead (`from_checkpoint`), also without a trainer.
"""

from __future__ import annotations

import io
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from hds.algo.continuation import kept_or_last
from hds.checkpoint import Checkpoints
from hds.networks import Policy
from hds.utils.io import atomic_write_bytes, atomic_write_json, read_json

FORMAT = "hds-policies/1"
KB = ("kernel", "bias")


def layer_names(params: dict) -> list[str]:
    """The network's layers in order: Dense_0, Dense_1, ..."""
    return sorted(params["params"], key=lambda n: int(n.rsplit("_", 1)[1]))


def save(directory: Path, module: Policy, params: dict, runs: list[dict], epochs) -> Path:
    """Write the batch's policies (`params`: stacked [n_runs, ...]) of `module` into
    directory, each run's seed and settings and the epoch its policy is from."""
    directory = Path(directory)
    names = layer_names(params)
    arrays = {f"{n}_{p}": np.asarray(params["params"][n][p]) for n in names for p in KB} | {
        "low": np.asarray(module.low),
        "high": np.asarray(module.high),
        "angular": np.asarray(module.angular),
    }
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    atomic_write_bytes(directory / "policy.npz", buffer.getvalue())
    spec = {
        "format": FORMAT,
        "network": {
            "hidden": [int(w) for w in module.hidden],
            "hinge_angles": [bool(a) for a in module.angular],
            "control_range": np.stack([module.low, module.high], 1).astype(float).tolist(),
            "activation": "tanh",
            "output": "mid + half * tanh(last layer): mid, half of each control range",
        },
        "layers": [{"kernel": f"{n}_kernel", "bias": f"{n}_bias"} for n in names],
        "runs": runs,
        "epochs": [int(e) for e in np.asarray(epochs)],
    }
    atomic_write_json(directory / "policy.json", spec)
    return directory


def load(directory: Path) -> tuple[Policy, dict, list[int]]:
    """(module, stacked parameters, each run's epoch) of a saved batch of policies."""
    directory = Path(directory)
    spec = read_json(directory / "policy.json")
    if spec.get("format") != FORMAT:
        raise ValueError(
            f"{directory}/policy.json has format {spec.get('format')!r}, not {FORMAT!r}: it was "
            "written by another version of hds; load it with that version"
        )
    with np.load(directory / "policy.npz") as npz:
        arrays = dict(npz)
    module = Policy(
        tuple(spec["network"]["hidden"]), arrays["angular"], arrays["low"], arrays["high"]
    )
    params = {
        "params": {
            layer["kernel"].removesuffix("_kernel"): {p: jnp.asarray(arrays[layer[p]]) for p in KB}
            for layer in spec["layers"]
        }
    }
    return module, params, spec["epochs"]


def from_checkpoint(directory: Path) -> tuple[dict, np.ndarray]:
    """(stacked parameters of the returned policies, each run's epoch) from the last readable
    checkpoint of a method's training (checkpoints/<method>), read as stored: no trainer gives
    its structure. The returned policy is the kept best where training kept one (algo.keep =
    best, progress.best) and found it, else the last iterate, as the trainer's final_policy."""
    state, _ = Checkpoints(directory).restore_stored()
    params, progress = state["policy"], state.get("progress") or {}
    if "best" in progress:
        kept = kept_or_last(progress["best"], progress["best_return"], params)
        params = jax.tree.map(np.asarray, kept)
    return params, np.asarray(state["epoch"])
