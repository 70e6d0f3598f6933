"""`retrain=true`: the policy's sim2real gap before and after the correction. PODS is trained
on the original simulator and on the corrected one (the same config, seeds and budget), and
each policy is evaluated on its own simulator and on the plant of `real` (the plant that
produced the data) from the same initial states."""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import OmegaConf

from hds.config import env_config

log = logging.getLogger("hds")


def retrain(cfg, corrected_env: dict, out_dir: Path) -> dict:
    from hds.envs import make_env
    from hds.experiment import Hooks, evaluate_training, method_logger, train
    from hds.real import make_plant

    plant = make_plant(cfg.real, cfg.env)
    rows = []
    for method, env_cfg in (("original", cfg.env), ("corrected", env_config(corrected_env))):
        log.info("retrain: PODS on the %s simulator", method)
        with method_logger(cfg, Path(out_dir), method, Hooks()) as logger:
            training = train(cfg, make_env(env_cfg), Path(out_dir), method, logger=logger)
            method_rows = evaluate_training(cfg, training, plant)
            logger.finish(method_rows, {})
        rows += method_rows
    plant_desc = {
        "plant": cfg.real.plant,
        "friction_gap": cfg.real.friction_gap,
        "effects": [OmegaConf.to_container(OmegaConf.structured(e)) for e in cfg.real.effects],
    }
    return {"plant": plant_desc, "rows": rows}
