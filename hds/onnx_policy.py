"""A trained policy as an ONNX model (`python -m hds.export ... format=onnx`), built layer by
layer with the `onnx` package's helper: the network is hds.networks.Policy, a few dense tanh
layers after the hinge angles' (sin, cos), so its graph is a handful of standard operators that
any ONNX runtime runs (onnxruntime, TensorRT, a robot's C++ stack).

jax2onnx, which traces any JAX function, was the other way; its releases pin orbax-checkpoint
below the version hds needs (0.17.1: <0.11.37, hds: 0.12.8) and bring equinox, dm-pix, netron
and huggingface-hub, for a graph this small (docs/export.md).

Input `obs` [batch, n_obs] float32 (the observations policy.json names); output `action`
[batch, n_act] float32 within the control range.
"""

from __future__ import annotations

import numpy as np

OPSET = 17  # ONNX 1.12 (2022): every operator used here, and what deployed runtimes still load
IR_VERSION = 8  # the IR of opset 17: runtimes older than the onnx package's newest IR load it
INPUT, OUTPUT = "obs", "action"


def build(
    layers: list[tuple[np.ndarray, np.ndarray]],
    hinge: np.ndarray,
    ctrl_range: np.ndarray,
    metadata: dict[str, str],
) -> bytes:
    """The serialized ONNX model of an MLP policy: `layers` (kernel [in, out], bias [out]) with
    tanh after each, the first fed [q of non-hinges, sin(hinges), cos(hinges), qd] of the
    observation (`hinge`: which of the nq positions are hinge angles), the last's tanh scaled
    onto `ctrl_range` [n_act, 2]; `metadata` goes into the model's metadata_props."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    hinge = np.asarray(hinge, bool)
    nq, n_obs = len(hinge), layers[0][0].shape[0] - int(hinge.sum())
    low, high = np.asarray(ctrl_range, np.float32).T
    nodes, inits = [], []

    def const(name: str, value: np.ndarray) -> str:
        inits.append(numpy_helper.from_array(np.asarray(value), name))
        return name

    def node(op: str, inputs: list[str], output: str, **attrs) -> str:
        nodes.append(helper.make_node(op, inputs, [output], **attrs))
        return output

    def columns(name: str, index) -> str:
        index = const(f"{name}_index", np.asarray(index, np.int64))
        return node("Gather", [INPUT, index], name, axis=-1)

    # the features of hds.networks.features; an empty part is left out (Gather of nothing)
    parts = []
    if (~hinge).any():
        parts.append(columns("q_other", np.flatnonzero(~hinge)))
    if hinge.any():
        angles = columns("angles", np.flatnonzero(hinge))
        parts += [node("Sin", [angles], "sin_angles"), node("Cos", [angles], "cos_angles")]
    parts.append(columns("qd", np.arange(nq, n_obs)))
    x = node("Concat", parts, "features", axis=-1) if len(parts) > 1 else parts[0]
    for i, (kernel, bias) in enumerate(layers):
        k = const(f"layer{i}_kernel", np.asarray(kernel, np.float32))
        b = const(f"layer{i}_bias", np.asarray(bias, np.float32))
        x = node("Add", [node("MatMul", [x, k], f"layer{i}_matmul"), b], f"layer{i}_linear")
        x = node("Tanh", [x], f"layer{i}_tanh")
    mid, half = const("mid", (high + low) / 2), const("half", (high - low) / 2)
    node("Add", [mid, node("Mul", [half, x], "scaled")], OUTPUT)
    graph = helper.make_graph(
        nodes,
        "hds_policy",
        [helper.make_tensor_value_info(INPUT, TensorProto.FLOAT, ["batch", n_obs])],
        [helper.make_tensor_value_info(OUTPUT, TensorProto.FLOAT, ["batch", len(low)])],
        inits,
    )
    model = helper.make_model(
        graph,
        opset_imports=[helper.make_opsetid("", OPSET)],
        ir_version=IR_VERSION,
        producer_name="hds",
    )
    helper.set_model_props(model, metadata)
    onnx.checker.check_model(model, full_check=True)
    return model.SerializeToString()
