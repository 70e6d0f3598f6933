"""`python -m hds.export run=<run dir> [method=...] [seed=...] [out=<dir>] [format=onnx]`:
write a trained policy as a self-contained directory that runs without JAX (default out:
<run dir>/export/<method>_<run>): policy.npz (weights), policy.json (observations, actions,
control range, dt, how observations enter the network, what the policy trained on), the MJCF
of the system it trained on and numpy_policy.py:

    import numpy_policy; policy = numpy_policy.load("<out>"); u = policy(obs)

format=onnx also writes policy.onnx (input `obs`, output `action`), for onnxruntime and the
robot stacks that load ONNX (docs/export.md).

(In Python: `hds.export_policy(policy, out_dir)`, hds/policy.py.)
"""

from __future__ import annotations

from pathlib import Path

from hds.config import SWEEP_KEYS
from hds.utils import cli

KEYS = {"run": Path, "method": str, "seed": int, **dict.fromkeys(SWEEP_KEYS, float), "out": Path}
KEYS["format"] = str  # json, onnx (hds.policy.FORMATS)


def main(argv: list[str]) -> Path:
    args, _ = cli.parse(argv, KEYS, "hds.export")
    setting = {k: args.pop(k) for k in SWEEP_KEYS if k in args}
    from hds.config import run_label
    from hds.policy import check_format, export_policy, load_policy

    check_format(args.get("format", "json"))  # before a checkpoint is read
    policy = load_policy(args["run"], args.get("method"), args.get("seed"), **setting)
    out = args.get("out") or args["run"] / "export" / f"{policy.method}_{run_label(policy.run)}"
    return export_policy(policy, out, args.get("format", "json"))


if __name__ == "__main__":
    print(f"wrote {cli.run(main)}")
