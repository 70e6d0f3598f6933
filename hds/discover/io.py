"""Reading the measured data of the command line, and the console summary."""

from __future__ import annotations

from pathlib import Path

from hds.data import format as data_format
from hds.data.format import Dataset

ROOT = Path(__file__).resolve().parents[2]  # the repository


def resolve(path: str | Path) -> Path:
    """A path as given, else relative to the repository's root (for configs' relative paths)."""
    p = Path(path).expanduser()
    if p.is_absolute() or p.exists():
        return p
    return ROOT / p if (ROOT / p).exists() else p


def load_dataset(path: str | Path, emps_cfg=None) -> Dataset:
    """A dataset file (.npz, .csv: hds.data.format), or an EMPS record (.mat: hds.data.emps)."""
    p = resolve(path)
    if p.suffix.lower() == ".mat":
        from hds.data import emps

        options = (
            {}
            if emps_cfg is None
            else {
                "dt": emps_cfg.dt,
                "segment": emps_cfg.segment,
                "cutoff": emps_cfg.cutoff,
                "order": emps_cfg.order,
            }
        )
        return emps.load(p, **options)
    return data_format.load(p)


def print_summary(result, out_dir: Path) -> None:
    from rich.table import Table

    from hds.logger import console

    table = Table(title="gap discovery: missing effects")
    for col in ("effect", "target", "parameters (95% CI)", "explained"):
        table.add_column(col)
    for e in result.missing_effects:
        table.add_row(e.name, e.target, e.fitted(units=True), f"{e.explained_fraction:.1%}")
    for t in result.terms:  # added to the corrected model too
        table.add_row(
            "joint_force_terms",
            t.joint,
            f"{t.coefficient:.4g} x {t.term} ({t.unit})",
            f"{t.share:.0%} of its force",
        )
    console.print(table)
    b, a = result.error("before"), result.error("after")
    with_terms = (
        f" ({result.after_terms['heldout'][1].normalized:.4g} with the terms)"
        if result.terms
        else ""
    )
    console.print(
        f"held-out k-step error (normalized RMSE): {b.normalized:.4g} -> "
        f"{a.normalized:.4g}{with_terms}; unexplained by the named effects "
        f"{result.unexplained_fraction:.1%}; left by the corrected model "
        f"{result.remainder_fraction:.1%} (measurement noise {result.noise_fraction:.1%})"
    )
    for w in result.warnings:
        console.print(f"[yellow]warning:[/yellow] {w}")
    console.print(f"report: {out_dir / 'report.md'}")
