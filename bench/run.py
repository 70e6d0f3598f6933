"""`python -m bench.run [SECTION ...] [--set SECTION.KEY=VALUE ...]` (`make bench`).

Sections (all by default: about 30 minutes on a 2-core CPU with the default budgets, more when
other processes compete for the cores):
  reference  the reference configuration end to end vs the reference implementation's 573 s
  overhead   the trainer's epoch over the bare engine cost of the same rollouts
  peers      brax's PPO and APG vs PODS and HDS: time and env steps to a return threshold
  peers_systems  the same on the double cart-pole swing-up (tree engine), 5 seeds: about 29
             minutes on its own on a shared 2-core CPU
  scaling    seeds vmapped, horizon, rollouts per epoch: wall time and peak memory
  compile    cold and warm (persistent cache) compile, each in its own process; every
             program a method of the study compiles: trace, lowering, XLA compile seconds
  engine     the tree engine vs brax generalized and MJX per system: compile, env-steps/s
  discovery  time to a gap-discovery report
  coverage   how often discovery's 95% intervals hold hidden effects (C MuJoCo plant, noise)
  sysid      EMPS fitted by IDIM-LS, hds discovery and mujoco.sysid (from the hand-off)
  terms      effects outside the library (a rail spring, pole drag) found as force terms
  gpu        skipped on CPU

Budgets are each section's DEFAULT_BUDGET; override a key with --set, e.g.
  python -m bench.run reference --set reference.backends=analytic --set reference.seeds=5
  python -m bench.run peers --set peers.tasks=cartpole_balance --set peers.pods_epochs=60
  python -m bench.run discovery --set discovery.backends=analytic,generalized
Values parse as JSON where they can (numbers, lists, true/false), else as a string; a
comma-separated value becomes a list. Each section's result replaces only its own entry of
bench/results.json, and bench/RESULTS.md is re-rendered from the whole file (`--out DIR` writes
them to DIR instead, leaving the committed ones alone).
"""

from __future__ import annotations

import argparse
import importlib
import json
import shlex
import sys
import time
import traceback
from pathlib import Path

import jax

from bench.common import ROOT, load_average, result_files, save_section, timed

SECTIONS = {
    "reference": "bench.reference",
    "overhead": "bench.overhead",
    "peers": "bench.peers",
    "peers_systems": "bench.peers_systems",
    "scaling": "bench.scaling",
    "compile": "bench.compilation",
    "engine": "bench.engine",
    "discovery": "bench.discovery",
    "coverage": "bench.coverage",
    "sysid": "bench.sysid",
    "terms": "bench.terms",
    "gpu": "bench.gpu",
}


def parse_value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        pass
    if "," in text:
        return [parse_value(part) for part in text.split(",") if part]
    return text


def budgets(names: list[str], settings: list[str]) -> dict[str, dict]:
    """Each selected section's default budget with the --set overrides applied; unknown
    sections or keys are refused, naming what exists."""
    out = {n: dict(importlib.import_module(SECTIONS[n]).DEFAULT_BUDGET) for n in names}
    for item in settings:
        key, sep, value = item.partition("=")
        section, dot, field = key.partition(".")
        if not (sep and dot):
            raise SystemExit(f"--set {item!r}: write SECTION.KEY=VALUE")
        if section not in out:
            raise SystemExit(
                f"--set {item!r}: section '{section}' is not selected; selected: {sorted(out)}"
            )
        if field not in out[section]:
            raise SystemExit(
                f"--set {item!r}: {section} has no budget key '{field}'; "
                f"keys: {sorted(out[section])}"
            )
        value = parse_value(value)
        if isinstance(out[section][field], list) and not isinstance(value, list):
            value = [value]  # a single backend where the default is a list of them
        out[section][field] = value
    return out


def run_section(name: str, budget: dict, command: str, files: tuple[Path, Path]) -> dict:
    """Run one section; a failure is recorded in its entry (with the traceback's tail) and
    does not stop the other sections."""
    module = importlib.import_module(SECTIONS[name])
    before = load_average()
    with timed() as t:
        try:
            result = module.run(budget)
        except Exception as err:  # noqa: BLE001 - recorded, and the next section still runs
            result = {
                "title": getattr(module, "TITLE", name),
                "error": f"{type(err).__name__}: {err}",
                "traceback": traceback.format_exc()[-4000:],
            }
    result.update(
        budget=budget, wall_s=t.s, load_before=before, load_after=load_average(), command=command
    )
    save_section(name, result, *files, merge=getattr(module, "merge", None))
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bench.run",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "sections",
        nargs="*",
        metavar="SECTION",
        help=f"sections to run, of {list(SECTIONS)} (default: all)",
    )
    parser.add_argument(
        "--set",
        dest="settings",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a budget value",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=ROOT / "bench",
        metavar="DIR",
        help="where results.json and RESULTS.md go (default: bench/, the committed ones)",
    )
    args = parser.parse_args(argv)
    unknown = [n for n in args.sections if n not in SECTIONS]
    if unknown:
        parser.error(f"unknown section(s) {unknown}; choose from {list(SECTIONS)}")
    names = args.sections or list(SECTIONS)
    selected = budgets(names, args.settings)
    args.out.mkdir(parents=True, exist_ok=True)
    files = result_files(jax.default_backend(), args.out)
    failed = []
    for name in names:
        command = (
            "python -m bench.run "
            + name
            + "".join(f" --set {shlex.quote(s)}" for s in args.settings if s.startswith(name + "."))
        )
        print(f"[bench] {name}: budget {selected[name]}", flush=True)
        start = time.strftime("%H:%M:%S")
        result = run_section(name, selected[name], command, files)
        status = (
            "skipped: " + result["skipped"]
            if result.get("skipped")
            else "FAILED: " + result["error"]
            if result.get("error")
            else "done"
        )
        print(f"[bench] {name} (started {start}) {status} in {result['wall_s']:.0f} s", flush=True)
        if result.get("error"):
            failed.append(name)
    print(f"[bench] wrote {files[0]} and {files[1]}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
