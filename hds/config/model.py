"""What validating a config needs of the MJCF model and of the device: env.xml compiled with
MuJoCo (the names effects may target, its sizes) and the memory a training program needs
against the device's (JAX). Imported by hds.config.validation only when a config is validated,
so that the schemas and composition import neither MuJoCo nor JAX.
"""

from __future__ import annotations

import math
import os

import jax

from hds.config.schemas import AlgoConfig
from hds.envs.system import load_spec, resolve_xml, target_names
from hds.utils.runtime import runs_vmapped

__all__ = ["check_memory", "effect_targets", "env_model", "memory_available", "resolve_xml"]


def effect_targets(xml: str) -> dict:
    """The names in env.xml that effects may target (hds.envs.system.target_names)."""
    return target_names(env_model(xml))


def check_memory(config) -> None:
    """Refuse a training program that cannot fit in memory, before it compiles. Its scratch
    memory grows with the rollouts of an epoch times their steps: per rollout and step, about
    32 + line_search + sum(algo.hidden) + 4 (nq + nv + nu) float32 numbers, for each run vmapped
    at once. That is 8 to 16% above `temp_size_in_bytes` of `memory_analysis()` of the compiled
    first-order `run_chunk` on the analytic cart-pole (rollouts 64 and 256, horizon 100 and
    200, line_search 8 and 16, hidden [64, 64] and [256, 256]); Gauss-Newton needs more."""
    if not isinstance(getattr(config, "algo", None), AlgoConfig):
        return
    algo, horizon = config.algo, config.env.task.horizon
    model = env_model(config.env.xml)
    numbers = 32 + algo.line_search + sum(algo.hidden) + 4 * (model.nq + model.nv + model.nu)
    runs = config.seeds * math.prod(len(v) for _, v in config.sweep.items())
    at_once = runs_vmapped(config.vmap_runs, runs)
    need = 4 * numbers * algo.rollouts * horizon * at_once
    have = memory_available()
    if need > have:
        raise ValueError(
            f"training needs about {need / 1e9:.3g} GB ({algo.rollouts} rollouts (algo.rollouts) "
            f"x {horizon} steps (env.task.horizon) x {at_once} run(s) at once x {4 * numbers} "
            f"bytes), and the device has {have / 1e9:.3g} GB: lower algo.rollouts, "
            "env.task.horizon or algo.hidden (or vmap_runs, to train fewer runs at once)"
        )


def env_model(xml: str):
    """env.xml's compiled MuJoCo model; a file MuJoCo cannot parse or compile is refused naming
    the key and the file (MuJoCo's own errors name neither)."""
    path = resolve_xml(xml)
    try:
        return load_spec(str(path)).compile()
    except ValueError as err:
        text = " ".join(str(err).split())
        if str(path) not in text:  # a compile error (load_spec's parse errors name the file)
            text = f"{path} does not compile as an MJCF model ({text}): fix it, or give another"
        raise ValueError(f"env.xml: {text} (env.xml=<path>)") from None


def memory_available() -> float:
    """Bytes of the default device: an accelerator's memory, or the host's on a CPU."""
    stats = jax.devices()[0].memory_stats() or {}
    if "bytes_limit" in stats:
        return float(stats["bytes_limit"])
    return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
