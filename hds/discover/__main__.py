"""`python -m hds.discover data=PATH [env=...] [retrain=true]`: gap discovery from the command
line. Writes report.md, report.json, plots/, conf/env/<env>_corrected.yaml, corrected.xml and
the mujoco.sysid hand-off (sysid/params.yaml, sysid/model.xml) to the run directory
(hydra.run.dir)."""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")

import hydra  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from hds.config import validate  # noqa: E402
from hds.discover import config as _schema  # noqa: E402,F401  (registers discover_schema)
from hds.discover.io import load_dataset  # noqa: E402
from hds.discover.report import corrected_env, write_report  # noqa: E402
from hds.discover.workflow import discover  # noqa: E402
from hds.rundir import print_one_line  # noqa: E402
from hds.utils.cli import check_command_line  # noqa: E402
from hds.utils.runtime import enable_compilation_cache  # noqa: E402

log = logging.getLogger("hds")


@hydra.main(config_path="../conf", config_name="discover", version_base="1.3")
def main(dcfg) -> float:
    try:
        cfg = validate(dcfg)  # every range check, before anything compiles
    except ValueError as err:
        print_one_line(err)
        raise
    enable_compilation_cache()
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    OmegaConf.save(dcfg, out_dir / "config.yaml", resolve=True)
    dataset = load_dataset(cfg.data, cfg.emps)
    validation = load_dataset(cfg.validation, cfg.emps) if cfg.validation else None
    result = discover(dataset, cfg.env, cfg.discover, validation)
    gaps = None
    if cfg.retrain:
        from hds.experiment import retrain

        gaps = retrain(cfg, corrected_env(cfg.env, result), out_dir)
    report = write_report(
        result,
        cfg.env,
        out_dir,
        cfg.discover.plot_episodes,
        cfg.discover.bins,
        gaps,
        data_name=str(cfg.data),
    )
    from hds.discover.io import print_summary

    handoff = report["sysid_handoff"]
    handed = ", ".join(handoff["handed_off"])
    log.info("mujoco.sysid hand-off: %s (%s)", out_dir / handoff["params"], handed)
    for line in handoff["not_handed_off"]:
        log.info("not handed off to mujoco.sysid: %s", line)
    print_summary(result, out_dir)
    return float(result.error("after").normalized)


if __name__ == "__main__":
    check_command_line(sys.argv[1:], "discover")
    main()
