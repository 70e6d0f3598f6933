"""`retrain=true`: the policy's sim2real gap before and after the correction. PODS is trained
on the original simulator and on the corrected one (the same config, seeds and budget), and
each policy is evaluated on its own simulator and on the plant of `real` (the plant that
produced the data) from the same initial states."""

from __future__ import annotations

import logging
from pathlib import Path

from omegaconf import OmegaConf

from hds.config import EnvConfig

log = logging.getLogger("hds")


def env_config(env: dict) -> EnvConfig:
    """A checked EnvConfig from a plain dict (e.g. the corrected env)."""
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(EnvConfig), env))
    cfg.check()
    for effect in cfg.effects:
        effect.check()
    return cfg


def retrain(cfg, corrected_env: dict, out_dir: Path) -> dict:
    from hds.envs import make_env
    from hds.evaluate import Evaluator, gap_rows
    from hds.real import make_plant
    from hds.run import batch_of, train

    plant = make_plant(cfg.real, cfg.env)
    rows = []
    for method, env_cfg in (("original", cfg.env), ("corrected", env_config(corrected_env))):
        env = make_env(env_cfg)
        log.info("retrain: PODS on the %s simulator", method)
        params, _, timing, logger, trainer = train(cfg, env, Path(out_dir), f"pods_{method}")
        evaluator = Evaluator(env, trainer.policy, plant, cfg.eval_episodes, cfg.eval_seed)
        method_rows = gap_rows(
            method, batch_of(cfg), evaluator.sim_returns(params), evaluator.real_returns(params)
        )
        if logger:
            logger.finish(method_rows, {})
        rows += method_rows
    plant_desc = {
        "plant": cfg.real.plant,
        "friction_gap": cfg.real.friction_gap,
        "effects": [OmegaConf.to_container(OmegaConf.structured(e)) for e in cfg.real.effects],
    }
    return {"plant": plant_desc, "rows": rows}
