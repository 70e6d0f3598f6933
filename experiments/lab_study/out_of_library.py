"""What the one-shot's discovery names on lab draws with and without some of their effects:
which named effects stand in for an effect the library has no law for.

    python experiments/lab_study/out_of_library.py --task cartpole_balance --signal prbs \\
        --without none backlash patch_friction backlash+patch_friction --draws 100 102 \\
        --out outputs/out_of_library

Each (draw, variant) is `python -m hds.run ... method=pods_corrected seeds=1 algo.epochs=2`
with the lab study's configs, on a plant with the draw's effects less the variant's (named by
effect, `+` between several; `none`: the whole draw) given as `real.effects` (no
`real.family`: a family's draw would put its effects back). Only discovery is read, so the
policy trains 2 epochs. A run that finished is read, not run again. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from report import family_of, named_vs_truth, study_experiment, unexplained  # noqa: E402

from hds.real import lab  # noqa: E402


def effect_override(effect: dict) -> str:
    """An effect as a Hydra override's dict, e.g. {name:backlash,target:slide,params:{...}}."""
    params = ",".join(f"{k}:{v!r}" for k, v in effect["params"].items())
    return f"{{name:{effect['name']},target:{effect['target']},params:{{{params}}}}}"


def variant(without: list[str]) -> str:
    """The removed effects' names as the table and the run directory show them."""
    return "+".join(without) or "none"


def overrides(task: str, draw: int, signal: str, without: list[str]) -> list[str]:
    """hds.run's overrides of one (draw, variant), less its run directory."""
    family = family_of(task)
    effects = [e for e in lab.effects(family, draw) if e["name"] not in without]
    name = f"{family}_{draw}_without_{variant(without).replace('+', '_')}"  # no '+' in a name
    return [
        f"env={task}", study_experiment(task), "real.family=", f"real.name={name}",
        "real.effects=[" + ",".join(effect_override(e) for e in effects) + "]",
        "method=pods_corrected", "seeds=1", "algo.epochs=2", f"dynamics.excitation={signal}",
    ]  # fmt: skip


def run(task: str, draw: int, signal: str, without: list[str], out: Path) -> Path:
    """The run's directory, running it first where it has no summary.json."""
    run_dir = out / f"{task}_{draw}_{signal}_without_{variant(without)}"
    if not (run_dir / "summary.json").exists():
        command = [
            sys.executable, "-m", "hds.run", "--config-dir", str(HERE / "conf"),
            *overrides(task, draw, signal, without), "hydra.mode=RUN", f"hydra.run.dir={run_dir}",
        ]  # fmt: skip
        print(f"{task} draw {draw}, {signal}, without {variant(without)}: running", flush=True)
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return run_dir


def row(task: str, draw: int, without: list[str], run_dir: Path) -> str:
    found = json.loads((run_dir / "summary.json").read_text())["discovery"]
    truth = lab.draw(family_of(task), draw)
    truth["effects"] = [e for e in truth["effects"] if e["name"] not in without]
    named = named_vs_truth(found["effects"], truth) or "nothing"
    left = unexplained(run_dir / "discovery")
    share = "-" if left is None else f"{100 * left:.1f}%"
    return f"| {draw} | {variant(without)} | {named} | {share} |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", required=True)
    parser.add_argument("--signal", default="steps", choices=["steps", "prbs"])
    parser.add_argument("--without", nargs="+", default=["none", "backlash"])
    parser.add_argument("--draws", type=int, nargs="+", required=True)
    parser.add_argument("--out", type=Path, default=Path("outputs/out_of_library"))
    args = parser.parse_args()
    variants = [[] if v == "none" else v.split("+") for v in args.without]
    known = {e["name"] for e in lab.effects(family_of(args.task), args.draws[0])}
    unknown = sorted({name for v in variants for name in v} - known)
    if unknown:
        parser.error(f"--without {unknown}: no such effect in the family; it has {sorted(known)}")
    lines = [
        "| draw | without | named vs truth (the truth less what was removed) | unexplained |",
        "| --- | --- | --- | --- |",
    ]
    for draw in args.draws:
        for without in variants:
            run_dir = run(args.task, draw, args.signal, without, args.out)
            lines.append(row(args.task, draw, without, run_dir))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
