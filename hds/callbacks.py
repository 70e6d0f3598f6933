"""Hydra callbacks: after a multirun, gather the jobs' summaries into the sweep directory."""

from __future__ import annotations

import logging
from pathlib import Path

from hydra.experimental.callback import Callback

from hds.logger import print_table
from hds.utils.io import atomic_write_json, read_json

log = logging.getLogger("hds")


def gather(sweep_dir: Path) -> dict:
    """One summary of every finished job below sweep_dir (each job's rows, tagged by job)."""
    rows, jobs = [], []
    for path in sorted(Path(sweep_dir).glob("*/summary.json"), key=lambda p: p.parent.name):
        summary = read_json(path)
        jobs.append(
            {"job": path.parent.name, "name": summary.get("name"), "real": summary.get("real")}
        )
        rows += [{**row, "job": path.parent.name} for row in summary["rows"]]
    failed = sorted(p.parent.name for p in Path(sweep_dir).glob("*/failed.txt"))
    return {"rows": rows, "jobs": jobs, "failed_jobs": failed}


class SweepSummary(Callback):
    def on_multirun_end(self, config, **kwargs) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        summary = gather(sweep_dir)
        if summary["rows"]:
            atomic_write_json(sweep_dir / "summary.json", summary)
            print_table(summary["rows"], title=f"{config.name}: every job of {sweep_dir}")
        if summary["failed_jobs"]:
            log.warning(
                "jobs %s failed (see their failed.txt); run the same sweep again, with "
                "hydra.sweep.dir=%s, to rerun them and skip the finished ones",
                summary["failed_jobs"],
                sweep_dir,
            )
