"""`python -m hds.run`: train a policy with PODS or HDS, measure its sim2real gap, record it all.

The command line over the experiment layer (hds/experiment.py): Hydra composes and validates the
config, names the run directory and runs sweeps; the experiment trains, evaluates and writes
summary.json, checkpoints/, plots/ and W&B logs. A run started again on the same directory
(`hydra.run.dir=...`) resumes from its checkpoints and ends with exactly the numbers an
uninterrupted run gives.
"""

from __future__ import annotations

import logging
import os
import traceback
from pathlib import Path

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")

from hds.utils.runtime import command_gc, enable_compilation_cache, headless_mujoco  # noqa: E402

headless_mujoco()  # before hds's modules import MuJoCo

import hydra  # noqa: E402
import numpy as np  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from hydra.types import RunMode  # noqa: E402

from hds import rundir  # noqa: E402
from hds.commands import before_hydra  # noqa: E402
from hds.config import validate  # noqa: E402
from hds.data.budget import check_planned  # noqa: E402
from hds.experiment import Hooks, run  # noqa: E402
from hds.gap import no_finite_result  # noqa: E402
from hds.simulators import method_name  # noqa: E402
from hds.utils import cli  # noqa: E402
from hds.utils.io import atomic_write_bytes  # noqa: E402

log = logging.getLogger("hds")


def wandb_group(hydra_cfg) -> str:
    """The W&B group of a run: its directory's last three parts (`multiruns/<name>/<time>` or
    `runs/<name>/<time>` by default). Every job of a multirun gets its sweep directory's, also
    when the sweep is started again on it; a single run gets its own. `logger.group=...`
    overrides it."""
    multirun = hydra_cfg.mode == RunMode.MULTIRUN
    directory = Path(str(hydra_cfg.sweep.dir if multirun else hydra_cfg.runtime.output_dir))
    return "/".join(directory.resolve().parts[-3:])[-128:]  # W&B allows 128 characters


def one_job_at_a_time(hydra_cfg) -> bool:
    """Whether this run has the terminal to itself: a single run, or a multirun on Hydra's basic
    launcher (jobs one after another); joblib's jobs run side by side, submitit's write files."""
    multirun = hydra_cfg.mode == RunMode.MULTIRUN
    return not multirun or str(hydra_cfg.launcher._target_).endswith(".BasicLauncher")


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(dcfg) -> float:
    hydra_cfg = HydraConfig.get()
    if dcfg.logger.group is None:
        dcfg.logger.group = wandb_group(hydra_cfg)
    out_dir = Path(hydra_cfg.runtime.output_dir)
    hydra_dir = out_dir / hydra_cfg.output_subdir if hydra_cfg.output_subdir else None
    try:
        with rundir.claim(out_dir, dcfg, hydra_dir):  # locked; its config.yaml is dcfg's
            cfg = validate(dcfg)  # every range check, before anything compiles
            check_planned(cfg)  # data past its limits: refused with its memory and time
            enable_compilation_cache()
            result = run(cfg, out_dir, Hooks(live_progress=one_job_at_a_time(hydra_cfg)))
        if failure := no_finite_result(result.rows):
            raise FloatingPointError(failure)
        # the sweeper's objective (hydra/sweeper=optuna: docs/sweeps.md) over the runs of the
        # run's own method (not the oracle trained beside it)
        own = [r for r in result.rows if r.method == method_name(cfg)]
        objective = float(np.mean([getattr(r, cfg.objective) for r in own]))
        if not np.isfinite(objective) and rundir.optimizing(hydra_cfg):
            raise FloatingPointError(
                f"{cfg.objective} is not finite ({objective}): a run of this trial diverged"
            )
    except Exception as err:
        if hydra_cfg.mode != RunMode.MULTIRUN:
            cli.exit_if_user_error(err)
            raise
        # One failed job must not stop the sweep: record why, let the others run. Starting
        # the sweep again reruns this job and skips the finished ones.
        atomic_write_bytes(out_dir / "failed.txt", traceback.format_exc().encode())
        log.exception("job %s failed; see %s", hydra_cfg.job.num, out_dir / "failed.txt")
        if rundir.optimizing(hydra_cfg):  # Optuna records the trial as failed and goes on; a NaN
            raise  # returned would stop its study (optuna rejects NaN values)
        return float("nan")
    (out_dir / "failed.txt").unlink(missing_ok=True)
    log.info("wrote %s", out_dir / "summary.json")
    return objective


if __name__ == "__main__":
    command_gc()
    before_hydra()
    main()
