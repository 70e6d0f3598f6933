"""Hydra callbacks: before a run, check that its directory can be written; after a multirun,
gather the jobs' summaries into the sweep directory, tell what the sweep found (hds.story: a
few lines per method, and a figure), and exit non-zero when a job failed."""

from __future__ import annotations

import logging
import sys
from dataclasses import replace
from pathlib import Path

from hydra.experimental.callback import Callback

from hds.results import Gathered, Summary
from hds.rundir import check_writable, optimizing
from hds.utils.io import atomic_write_json

log = logging.getLogger("hds")


def gather(sweep_dir: Path) -> Gathered:
    """One summary of every finished job below sweep_dir (each job's rows, those on its
    further plants included, tagged by job)."""
    rows, jobs = [], []
    for path in sorted(Path(sweep_dir).glob("*/summary.json"), key=lambda p: p.parent.name):
        if (path.parent / "failed.txt").exists():
            continue  # refused on a restart: its summary is another configuration's
        summary, job = Summary.read(path), path.parent.name
        jobs.append({"job": job, "name": summary.name, "real": summary.real or None})
        rows += [replace(row, job=job) for row in summary.rows + summary.rows_eval_plants]
    failed = sorted(p.parent.name for p in Path(sweep_dir).glob("*/failed.txt"))
    return Gathered(rows, jobs, failed)


def tell(name: str, sweep_dir: Path, jobs: int, loops: list[Path]) -> None:
    """The sweep's last words: a few lines per method (hds.story), not a row per seed (those
    are in summary.json, loop.json and `python -m hds.report`'s report.csv), and its figure."""
    from hds.report import sweep_story

    try:
        text, figure = sweep_story(sweep_dir)
    except Exception as err:  # a convenience: it must not hide the jobs' exit code below
        log.warning("could not summarize %s: %s: %s", sweep_dir, type(err).__name__, err)
        return
    rows_in = sweep_dir / "summary.json"
    rows_in = rows_in if rows_in.is_file() else loops[0].parent
    print(f"\n{name}: {jobs} job{'s' if jobs != 1 else ''} in {sweep_dir}\n")
    print(text)
    print(
        f"\nfigure: {figure}\nevery seed's row: {rows_in}; "
        f"the full report: python -m hds.report dir={sweep_dir}"
    )


class SweepSummary(Callback):
    def on_multirun_end(self, config, **kwargs) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        summary = gather(sweep_dir)
        if summary.rows:
            atomic_write_json(sweep_dir / "summary.json", summary.to_json())
        loops = sorted(sweep_dir.glob("*/loop.json"))  # hds.loop's jobs: rows in loop.json
        if summary.rows or loops:
            tell(config.name, sweep_dir, len(summary.jobs) + len(loops), loops)
        if failed := summary.failed_jobs:
            # a finished job refused on a restart (another configuration) has both files
            total = len({*failed, *(j["job"] for j in summary.jobs)})
            if optimizing(config.hydra):  # a failed trial is part of a search, not an error
                log.warning(
                    "%d of %d trials failed: %s (see their failed.txt); Optuna recorded them "
                    "as failed trials",
                    len(failed),
                    total,
                    ", ".join(failed),
                )
                return
            sys.exit(
                f"error: {len(failed)} of {total} jobs failed: "
                f"{', '.join(failed)} (see their failed.txt); run the same sweep again, with "
                f"hydra.sweep.dir={sweep_dir}, to rerun them and skip the finished ones"
            )


class StartChecks(Callback):
    """What Hydra itself would fail on unclearly, checked before anything runs: a run or sweep
    directory that cannot be written (Hydra's log-file error hides the path), and a launcher
    timeout that gives the jobs no time (submitit then fails with no job directory)."""

    def on_run_start(self, config, **kwargs) -> None:
        check_writable(config.hydra.run.dir, "hydra.run.dir")

    def on_multirun_start(self, config, **kwargs) -> None:
        check_writable(config.hydra.sweep.dir, "hydra.sweep.dir")
        timeout = config.hydra.launcher.get("timeout_min")
        if timeout is not None and timeout < 1:
            sys.exit(
                f"error: hydra.launcher.timeout_min = {timeout} gives every job no time: give "
                "the minutes a job may run (at least 1)"
            )
