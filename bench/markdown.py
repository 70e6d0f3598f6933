"""Render bench/results.json into bench/RESULTS.md.

A section's result holds `title`, `budget`, `tables` ([{caption, columns, rows}]), `notes`,
optionally `targets` ([{target, value, met}]) and `skipped` (why nothing was measured), and the
raw numbers under `data`; this module only lays them out.
"""

from __future__ import annotations

import numpy as np

ORDER = (
    "reference",
    "overhead",
    "peers",
    "peers_systems",
    "scaling",
    "compile",
    "engine",
    "discovery",
    "gpu",
)


def fmt(x, digits: int = 3) -> str:
    """A number for a table: thousands separators, `digits` significant figures for small ones."""
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int | np.integer):
        return f"{int(x):,}"
    x = float(x)
    if not np.isfinite(x):
        return str(x)
    if abs(x) >= 1000:
        return f"{x:,.0f}"
    return f"{x:.{digits}g}"


def _cell(x) -> str:
    return fmt(x).replace("|", "\\|")


def table(columns, rows) -> list[str]:
    lines = ["| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return lines


def machine_lines(machine: dict) -> list[str]:
    v = machine.get("versions", {})
    return [
        f"- CPU: {machine.get('cpu')}, {machine.get('cores')} cores, "
        f"{machine.get('memory_gib')} GiB memory; {machine.get('platform')}",
        f"- Python {machine.get('python')}; jax {v.get('jax')} (jaxlib {v.get('jaxlib')}, "
        f"backend {machine.get('jax_backend')}), brax {v.get('brax')}, flax {v.get('flax')}, "
        f"optax {v.get('optax')}, mujoco {v.get('mujoco')}",
    ] + [f"- Accelerator: {kind}" for kind in machine.get("accelerators", [])]


def section_lines(name: str, sec: dict) -> list[str]:
    lines = [f"## {name}: {sec.get('title', '')}", ""]
    lines.append(
        f"Measured {sec.get('measured_at')}; load average before/after "
        f"{sec.get('load_before')} / {sec.get('load_after')}; section wall time "
        f"{_cell(sec.get('wall_s'))} s. "
        f"Command: `{sec.get('command', 'python -m bench.run ' + name)}`."
    )
    if sec.get("budget"):
        budget = ", ".join(f"{k}={v}" for k, v in sec["budget"].items())
        lines += ["", f"Budget: {budget}."]
    if sec.get("skipped"):
        lines += ["", f"**Skipped:** {sec['skipped']}"]
    if sec.get("error"):
        lines += ["", f"**Failed:** {sec['error']}"]
    for t in sec.get("tables", []):
        lines += ["", f"**{t['caption']}**", ""] + table(t["columns"], t["rows"])
    if sec.get("targets"):
        lines += ["", "Targets:", ""]
        lines += table(
            ["target", "measured", "met"],
            [[t["target"], t["value"], t["met"]] for t in sec["targets"]],
        )
    if sec.get("notes"):
        lines += [""] + [f"- {n}" for n in sec["notes"]]
    return lines + [""]


def render(results: dict) -> str:
    sections = results.get("sections", {})
    names = [n for n in ORDER if n in sections] + sorted(set(sections) - set(ORDER))
    lines = [
        "# hds benchmarks",
        "",
        "Written by `python -m bench.run` (`make bench`); `python -m bench.run SECTION ...` "
        "re-measures only those sections. Raw numbers: `bench/results.json` (a GPU's: "
        "`bench/results-gpu.json`). Benchmarks measure and report; no timing is asserted anywhere. "
        "Each section records the machine's load average before and after it: on a shared "
        "machine, other processes slow compiles and runs alike, so compare rows measured "
        "under similar load.",
        "",
    ]
    latest = max(sections.values(), key=lambda s: s.get("measured_at", ""), default=None)
    if latest:
        lines += ["Machine (of the latest section):", ""] + machine_lines(latest["machine"]) + [""]
    glance = [
        [name, t["target"], t["value"], t["met"]]
        for name in names
        for t in sections[name].get("targets", [])
    ]
    if glance:
        lines += ["## Targets at a glance", ""]
        lines += table(["section", "target", "measured", "met"], glance) + [""]
    for name in names:
        lines += section_lines(name, sections[name])
    return "\n".join(lines).rstrip() + "\n"
