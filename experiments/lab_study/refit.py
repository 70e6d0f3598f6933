"""A loop round's work again with this checkout's code, on the round's own data: its hybrid
model refitted and judged (`model`), or its discovery on the loop's data so far
(`discover`). What a fix changes, measured on a finished study's loops without rerunning them.

    python experiments/lab_study/refit.py model outputs/study/lab/cartpole_balance/hybrid/d0 2
    python experiments/lab_study/refit.py discover outputs/study/lab/furuta_balance/loop/d1 3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
from pathlib import Path

import jax

from hds.config.composition import load_config
from hds.config.schemas import EffectConfig
from hds.data import load
from hds.data.format import concatenate


def refit_model(loop_dir: Path, r: int) -> None:
    """Round r's hybrid fitted on its model_data.npz, on its simulator (the loop's env with the
    round's named effects), against the round's recorded k-step errors."""
    from hds.dynamics import build
    from hds.envs import make_env

    cfg, rdir = load_config(loop_dir / "config.yaml"), loop_dir / "rounds" / str(r)
    report = json.loads((rdir / "round.json").read_text())
    named = [EffectConfig(e["name"], e["target"], e["params"]) for e in report["effects"]]
    env = make_env(dataclasses.replace(cfg.env, effects=[*cfg.env.effects, *named]))
    dyn = dataclasses.replace(cfg.dynamics, data=str(rdir / "model_data.npz"))
    _, now = build(dyn, env, None, jax.random.PRNGKey(cfg.seed), Path(tempfile.mkdtemp()))
    before = report["model"]
    print(f"{loop_dir} round {r}: {', '.join(f'{e.name}@{e.target}' for e in named)}")
    for k in sorted(now["multistep"], key=int):
        n, b = now["multistep"][k], before["multistep"][k]
        print(
            f"  k={k}: model / simulator {n['model']:.3g} / {n['simulator']:.3g} "
            f"(the round's: {b['model']:.3g} / {b['simulator']:.3g})"
        )
    print(f"  used: {now['used']} (the round's: {before['used']})")


def rediscover(loop_dir: Path, r: int) -> None:
    """Discovery on the data of rounds 1 to r, as round r ran it."""
    from hds.discover import discover

    cfg = load_config(loop_dir / "config.yaml")
    data = concatenate([load(loop_dir / "rounds" / str(k) / "data.npz") for k in range(1, r + 1)])
    result = discover(data, cfg.env, cfg.discover)
    for e in result.missing_effects:
        print(f"  named {e.name}@{e.target} {e.to_json()['params']}")
    print(f"  unexplained {result.unexplained_fraction:.1%}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("what", choices=["model", "discover"])
    parser.add_argument("loop_dir", type=Path)
    parser.add_argument("round", type=int)
    args = parser.parse_args()
    (refit_model if args.what == "model" else rediscover)(args.loop_dir, args.round)


if __name__ == "__main__":
    main()
