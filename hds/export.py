"""`python -m hds.export run=<run dir> [method=...] [seed=...] [out=<dir>]`: write a trained
policy as a self-contained directory that runs without JAX (default out: <run dir>/export/
<method>_<run>): policy.npz (weights), policy.json (observations, actions, control range, dt,
how observations enter the network), the system's MJCF and numpy_policy.py:

    import numpy_policy; policy = numpy_policy.load("<out>"); u = policy(obs)

(In Python: `hds.export(policy, out_dir)`, hds/policy.py.)
"""

from __future__ import annotations

from pathlib import Path

from hds.config import SWEEP_KEYS
from hds.utils import cli

KEYS = {"run": Path, "method": str, "seed": int, **dict.fromkeys(SWEEP_KEYS, float), "out": Path}


def main(argv: list[str]) -> Path:
    args, _ = cli.parse(argv, KEYS, "hds.export")
    setting = {k: args.pop(k) for k in SWEEP_KEYS if k in args}
    from hds.config import run_label
    from hds.policy import export, load_policy

    policy = load_policy(args["run"], args.get("method"), args.get("seed"), **setting)
    out = args.get("out") or args["run"] / "export" / f"{policy.method}_{run_label(policy.run)}"
    return export(policy, out)


if __name__ == "__main__":
    print(f"wrote {cli.run(main)}")
