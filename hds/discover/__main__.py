"""`python -m hds.discover data=PATH [env=...] [retrain=true]`: gap discovery from the command
line. Writes report.md, report.json, plots/, conf/env/<env>_corrected.yaml, corrected.xml and
the mujoco.sysid hand-off (sysid/params.yaml, sysid/model.xml) to the run directory
(hydra.run.dir)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")

from hds.utils.runtime import enable_compilation_cache, headless_mujoco  # noqa: E402

headless_mujoco()  # before hds's modules import MuJoCo

import hydra  # noqa: E402
from hydra.core.hydra_config import HydraConfig  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from hds.commands import before_hydra  # noqa: E402
from hds.config import validate  # noqa: E402
from hds.data.budget import DISCOVERY, check_dataset  # noqa: E402
from hds.discover import config as _schema  # noqa: E402,F401  (registers discover_schema)
from hds.discover.data import check_size  # noqa: E402
from hds.discover.io import load_dataset  # noqa: E402
from hds.discover.workflow import discover  # noqa: E402
from hds.discover.write import corrected_env, write_report  # noqa: E402
from hds.utils import cli  # noqa: E402

log = logging.getLogger("hds")


@hydra.main(config_path="../conf", config_name="discover", version_base="1.3")
def main(dcfg) -> float:
    with cli.one_line_errors():  # bad config or data: one line (docs/cli.md)
        return run(dcfg, Path(HydraConfig.get().runtime.output_dir))


def load_data(cfg):
    """The dataset and the validation dataset of a validated config, each checked against the
    env and within discover.max_steps, before anything compiles."""
    from hds.data.format import validate as check_data
    from hds.envs.system import data_interface

    sim = data_interface(cfg.env.xml, cfg.env.timestep)
    datasets = []
    for key in ("data", "validation"):
        path = getattr(cfg, key)
        if path is None:
            datasets.append(None)
            continue
        dataset = check_data(load_dataset(path, cfg.emps), sim, where=f"{key} = {path}")
        check_dataset(DISCOVERY, dataset, cfg.discover.max_steps, f"{key} = {path}")
        datasets.append(dataset)
    return datasets


def run(dcfg, out_dir: Path) -> float:
    cfg = validate(dcfg)  # every range check, before anything compiles
    dataset, validation = load_data(cfg)
    check_size(dataset, cfg.discover.horizon, f"data = {cfg.data}")  # enough to identify
    enable_compilation_cache()
    OmegaConf.save(dcfg, out_dir / "config.yaml", resolve=True)
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
    before_hydra("discover")
    main()
