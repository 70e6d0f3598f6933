"""What a run shows and records: a progress bar, W&B offline logs, a final table (`conf/logger`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

console = Console()


class RunLogger:
    def __init__(self, cfg, out_dir: Path, name: str, total_epochs: int, start_epoch: int = 0):
        self.wandb = None
        if cfg.logger.wandb:
            os.environ.setdefault("WANDB_SILENT", "true")
            import wandb

            self.wandb = wandb.init(
                project=cfg.logger.project,
                group=cfg.logger.group,
                name=name,
                dir=str(out_dir),
                mode=cfg.logger.mode,
                config=_flat(cfg),
                reinit="create_new",
            )
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
        self.task = self.progress.add_task(name, total=total_epochs, completed=start_epoch, ret="-")
        self.progress.start()

    def log_epochs(self, first_epoch: int, metrics: dict, seconds_per_epoch: float) -> None:
        """`metrics`: {name: [n_seeds, n_epochs]} for epochs first_epoch, first_epoch + 1, ..."""
        n = next(iter(metrics.values())).shape[1]
        for i in range(n):
            row = {k: float(np.nanmean(v[:, i])) for k, v in metrics.items()}
            if self.wandb:
                row |= {
                    f"{k}/seed{s}": float(v[s, i])
                    for k, v in metrics.items()
                    for s in range(v.shape[0])
                }
                self.wandb.log(
                    row | {"epoch": first_epoch + i, "wall_time_per_epoch": seconds_per_epoch}
                )
        self.progress.update(
            self.task, advance=n, ret=f"{np.nanmean(metrics['return'][:, -1]):.1f}"
        )

    def finish(self, rows: list[dict], figures: dict) -> None:
        self.progress.stop()
        if self.wandb:
            import wandb

            keys = list(rows[0])
            self.wandb.log(
                {"summary": wandb.Table(columns=keys, data=[[r[k] for k in keys] for r in rows])}
            )
            self.wandb.log({name: wandb.Image(fig) for name, fig in figures.items()})
            self.wandb.finish()
        import matplotlib.pyplot as plt

        for fig in figures.values():
            plt.close(fig)


def print_table(rows: list[dict], title: str = "sim2real") -> None:
    """Every column of the rows, in their order: method, seed, swept settings, returns, gaps."""
    table = Table(title=title)
    keys = list(dict.fromkeys(k for r in rows for k in r))  # rows of a sweep's jobs may differ
    for k in keys:
        table.add_column(k, justify="left" if k == "method" else "right")
    for r in rows:
        table.add_row(*[_cell(k, r.get(k, "")) for k in keys])
    console.print(table)


def _cell(key: str, value) -> str:
    if key == "gap_relative":
        return f"{value:.1%}"
    return f"{value:.1f}" if isinstance(value, float) else str(value)


def _flat(cfg) -> dict:
    from dataclasses import asdict

    return asdict(cfg)
