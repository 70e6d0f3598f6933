"""What a run shows and records: a progress bar, W&B offline logs, a final table (`conf/logger`)."""

from __future__ import annotations

import hashlib
import html
import os
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from hds.config import run_label
from hds.results import Row

console = Console()


def wandb_id(out_dir: Path, method: str) -> str:
    """The W&B run id of a method's training in a run directory: the same when the run is
    started again on that directory, so a resumed run continues its W&B run."""
    return hashlib.sha1(f"{Path(out_dir).resolve()}:{method}".encode()).hexdigest()[:16]


class RunLogger:
    """One method's training: a progress bar and, with logger.wandb, a W&B run whose metrics
    are stepped by epoch, labelled per run by seed and swept setting, and whose summary holds
    the final returns and gaps. `close` ends both, also when training failed."""

    def __init__(self, cfg, out_dir: Path, method: str, runs: list[dict], console=True, live=True):
        self.cfg, self.out_dir, self.method = cfg, Path(out_dir), method
        self.labels = [run_label(r) for r in runs]
        self.show, self.live = console, live
        self.epoch, self.started = 0, time.perf_counter()
        self.wandb = self.progress = None

    def start(self, first_epoch: int) -> None:
        if self.cfg.logger.wandb:
            os.environ.setdefault("WANDB_SILENT", "true")
            import wandb

            self.wandb = wandb.init(
                project=self.cfg.logger.project,
                group=self.cfg.logger.group,
                name=self.method,
                id=wandb_id(self.out_dir, self.method),
                resume="allow",
                dir=str(self.out_dir),
                mode=self.cfg.logger.mode,
                config=_flat(self.cfg),
                reinit="create_new",
            )
            self.wandb.define_metric("epoch")
            self.wandb.define_metric("*", step_metric="epoch")
        self.epoch = first_epoch
        if self.show and self.live:
            self.progress = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                TextColumn("epoch {task.completed}/{task.total}"),
                TextColumn("return {task.fields[ret]}"),
                TimeElapsedColumn(),
                TimeRemainingColumn(),
                console=console,
                transient=False,
            )
            self.task = self.progress.add_task(
                self.method, total=self.cfg.algo.epochs, completed=first_epoch, ret="-"
            )
            self.progress.start()

    def log_epochs(self, first_epoch: int, metrics: dict, seconds_per_epoch: float) -> None:
        """`metrics`: {name: [n_runs, n_epochs]} for epochs first_epoch, first_epoch + 1, ..."""
        n = next(iter(metrics.values())).shape[1]
        if self.wandb:
            for i in range(n):
                row = {k: _finite_mean(v[:, i]) for k, v in metrics.items()}
                row |= {
                    f"{k}/{label}": float(v[s, i])
                    for k, v in metrics.items()
                    for s, label in enumerate(self.labels)
                }
                row |= {"epoch": first_epoch + i + 1, "wall_time_per_epoch": seconds_per_epoch}
                self.wandb.log(row)
        self.epoch += n
        ret = _finite_mean(metrics["return"][:, -1])
        shown = f"{ret:.1f}" if np.isfinite(ret) else "diverged (every rollout non-finite)"
        if self.progress:
            self.progress.update(self.task, advance=n, ret=shown)
        elif self.show and self._tenth_crossed(n):
            # a line at each tenth of the epochs: jobs running side by side share the terminal
            elapsed = time.perf_counter() - self.started
            console.print(
                f"{self.method} epoch {self.epoch}/{self.cfg.algo.epochs} return {shown} "
                f"({elapsed:.0f} s)",
                highlight=False,
            )

    def _tenth_crossed(self, n: int) -> bool:
        """Whether the last n epochs crossed a tenth of the run's epochs (or ended it)."""
        total = self.cfg.algo.epochs
        tenth = max(total // 10, 1)
        return self.epoch // tenth > (self.epoch - n) // tenth or self.epoch >= total

    def finish(self, rows: list[Row], figures: dict) -> None:
        """The final rows (one per run) as a table and as summary scalars, and the figures."""
        if self.wandb:
            import wandb

            table = [r.to_json() for r in rows]
            keys = list(table[0])
            self.wandb.log(
                {"summary": wandb.Table(columns=keys, data=[[r[k] for k in keys] for r in table])}
            )
            for key in ("sim_return", "real_return", "gap"):
                values = [getattr(r, key) for r in rows]
                self.wandb.summary[f"{key}/mean"] = float(np.mean(values))
                for value, label in zip(values, self.labels):
                    self.wandb.summary[f"{key}/{label}"] = value
            self.wandb.log({name: wandb.Image(fig) for name, fig in figures.items()})
        import matplotlib.pyplot as plt

        for fig in figures.values():
            plt.close(fig)

    def log_files(self, files: dict[str, Path]) -> None:
        """Media a person opens (a GIF as a video, an HTML page as it is, other text as
        HTML-escaped text)."""
        if not self.wandb:
            return
        import wandb

        for name, path in files.items():
            if path.suffix == ".gif":
                self.wandb.log({name: wandb.Video(str(path), format="gif")})
            elif path.suffix == ".html":
                self.wandb.log({name: wandb.Html(path.read_text())})
            else:
                self.wandb.log({name: wandb.Html(f"<pre>{html.escape(path.read_text())}</pre>")})

    def log_discovery(self, name: str, directory: Path) -> None:
        """A gap-discovery report (hds.discover's directory) as W&B media: its page
        (report.html), each figure as an image and the named effects and their correlations
        as tables, under `name/`."""
        if not self.wandb:
            return
        import wandb

        from hds.utils.io import read_json

        directory = Path(directory)
        self.log_files({name: directory / "report.html"})
        media = {
            f"{name}/{png.stem}": wandb.Image(str(png))
            for png in sorted((directory / "plots").glob("*.png"))
        }
        report = read_json(directory / "report.json")
        columns = ["effect", "target", "parameter", "value", "ci95_low", "ci95_high", "explained"]
        effects = [
            [e["name"], e["target"], p, v, *(e["ci95"].get(p) or [None, None])]
            + [e["explained_fraction"]]
            for e in report.get("missing_effects", [])
            for p, v in e["params"].items()
        ]
        media[f"{name}/named_effects"] = wandb.Table(columns=columns, data=effects)
        pairs = [
            [r["a"], r["b"], r["rho"], r["inseparable"]] for r in report.get("correlations", [])
        ]
        if pairs:
            media[f"{name}/correlations"] = wandb.Table(
                columns=["parameter", "parameter", "correlation", "inseparable"], data=pairs
            )
        self.wandb.log(media)

    def close(self, failed: bool = False) -> None:
        if self.progress:
            self.progress.stop()
            self.progress = None
        if self.wandb:
            self.wandb.finish(exit_code=1 if failed else 0)
            self.wandb = None


def _finite_mean(values) -> float:
    """The mean of the finite values; NaN (silently) when there is none."""
    values = np.asarray(values, dtype=float)
    finite = values[np.isfinite(values)]
    return float(finite.mean()) if finite.size else float("nan")


def print_table(rows: list[Mapping], title: str = "sim2real") -> None:
    """Every column of the rows (`hds.results.Row`s, or any flat mappings), in their order:
    method, seed, swept settings, returns, gaps."""
    rows = [r.to_json() if isinstance(r, Row) else r for r in rows]
    table = Table(title=title)
    keys = list(dict.fromkeys(k for r in rows for k in r))  # rows of a sweep's jobs may differ
    for k in keys:
        table.add_column(k, justify="left" if k == "method" else "right")
    cells = [[_cell(k, r.get(k, "")) for k in keys] for r in rows]
    for row in cells:
        table.add_row(*row)
    # wide enough for every header and cell whole, also where the console is not a terminal
    widths = [max(len(k), *(len(row[i]) for row in cells)) for i, k in enumerate(keys)]
    width = max(console.width, sum(w + 4 for w in widths) + 2)
    Console(file=console.file, width=width, force_terminal=console.is_terminal).print(table)


def _cell(key: str, value) -> str:
    """Returns and gaps to one decimal; swept settings (step size 0.01 beside 0.04) as %g."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if key == "gap_relative":
        return f"{value:.1%}"
    if key in ("sim_return", "real_return", "gap"):
        return f"{value:.1f}"
    return f"{value:g}" if isinstance(value, float) else str(value)


def _flat(cfg) -> dict:
    from dataclasses import asdict

    return asdict(cfg)
