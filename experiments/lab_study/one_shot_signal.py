"""The one-shot corrected simulator on lab draws with each excitation signal: what discovery
names against the draw's truth, the policy's real return, the plant time the data took.

    python experiments/lab_study/one_shot_signal.py --task furuta_balance \\
        --draws 100 102 104 105 123 --signals steps prbs --out outputs/one_shot_signal

Each (draw, signal) is `python -m hds.run ... method=pods_corrected seeds=1
dynamics.excitation=<signal>` with the lab study's configs (`lab_study[_furuta]`,
`lab_task_<task>`), in its own run directory under --out; a run that finished is read, not run
again. Prints a markdown table.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from omegaconf import OmegaConf  # noqa: E402
from report import family_of, named_vs_truth, study_experiment  # noqa: E402

from hds.real import lab  # noqa: E402


def run(task: str, draw: int, signal: str, out: Path) -> Path:
    """The run's directory, running it first where it has no summary.json."""
    run_dir = out / f"{task}_{draw}_{signal}"
    if not (run_dir / "summary.json").exists():
        command = [
            sys.executable, "-m", "hds.run", "--config-dir", str(HERE / "conf"),
            f"env={task}", study_experiment(task),
            f"real.draw={draw}", "method=pods_corrected", "seeds=1",
            f"dynamics.excitation={signal}", "hydra.mode=RUN", f"hydra.run.dir={run_dir}",
        ]  # fmt: skip
        print(f"{task} draw {draw}, {signal}: running", flush=True)
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    return run_dir


def row(task: str, draw: int, signal: str, run_dir: Path) -> str:
    """The table's row of one run: the delay's truth, what discovery named against the
    truth, the real (and simulated) return, the plant seconds of every record."""
    truth = lab.draw(family_of(task), draw)
    delay = [e["params"]["steps"] for e in truth["effects"] if e["name"] == "action_delay"]
    summary = json.loads((run_dir / "summary.json").read_text())
    cfg = OmegaConf.load(run_dir / "config.yaml")
    found, result = summary["discovery"], summary["rows"][0]
    named = named_vs_truth(found["effects"], truth) or "nothing"
    dt = cfg.env.timestep * cfg.env.frames_per_step
    plant_s = found["episodes"] * cfg.dynamics.horizon * dt
    return (
        f"| {draw} | {signal} | {delay[0] if delay else 0} | {named} | "
        f"{result['real_return']:.2f} ({result['sim_return']:.2f}) | {plant_s:.0f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", required=True, choices=["cartpole_balance", "furuta_balance"])
    parser.add_argument("--draws", type=int, nargs="+", required=True)
    parser.add_argument("--signals", nargs="+", default=["steps", "prbs"])
    parser.add_argument("--out", type=Path, default=Path("outputs/one_shot_signal"))
    args = parser.parse_args()
    lines = [
        "| draw | signal | truth: delay steps | named vs truth | real return (sim) | plant s |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for draw in args.draws:
        for signal in args.signals:
            lines.append(row(args.task, draw, signal, run(args.task, draw, signal, args.out)))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
