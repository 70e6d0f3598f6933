"""The configuration: the structured schemas of every `conf/` group, their validation, and
composing and loading configs. Every name is importable from `hds.config`:

  schemas       one dataclass per group (Config, EnvConfig, AlgoConfig, ...), registered with
                Hydra on import so that an unknown key or a wrong type fails at composition;
                each has a `check()` of its ranges
  validation    validate(cfg): every check, no unknown key, finite numbers, effects against
                the model, and the memory a training program needs (hds.config.model, which
                compiles the MJCF and asks JAX: imported only when a config is validated)
  composition   compose(overrides) as the commands compose; load_config(config.yaml);
                env_config(dict); the overrides of a command line
  kinds         the simulator kinds `simulator=` may name, declared by name with the light
                facts the checks read (their classes: hds.simulators, imported when built)
"""

from hds.config.composition import (
    CONF_DIR,
    SweepSettings,
    cli_overrides,
    compose,
    config_groups,
    env_config,
    load_config,
    schema_of,
    sweep_settings,
)
from hds.config.schemas import (
    SEED_MAX,
    SWEEP_KEYS,
    AlgoConfig,
    AnnealConfig,
    Config,
    DiscoverAppConfig,
    DiscoverConfig,
    DRConfig,
    DynamicsConfig,
    EffectConfig,
    EmpsConfig,
    EnvConfig,
    LoggerConfig,
    LoopConfig,
    NoiseConfig,
    PathsConfig,
    RangedEffectConfig,
    RealConfig,
    SweepConfig,
    TaskConfig,
    plant_has_effects,
    register,
    run_label,
)
from hds.config.validation import (
    FLOAT32_MAX,
    check_override_keys,
    validate,
)

__all__ = [
    "AlgoConfig",
    "AnnealConfig",
    "CONF_DIR",
    "Config",
    "DRConfig",
    "DiscoverAppConfig",
    "DiscoverConfig",
    "DynamicsConfig",
    "EffectConfig",
    "EmpsConfig",
    "EnvConfig",
    "FLOAT32_MAX",
    "LoggerConfig",
    "LoopConfig",
    "NoiseConfig",
    "PathsConfig",
    "RangedEffectConfig",
    "RealConfig",
    "SEED_MAX",
    "SWEEP_KEYS",
    "SweepConfig",
    "SweepSettings",
    "TaskConfig",
    "check_override_keys",
    "cli_overrides",
    "compose",
    "config_groups",
    "env_config",
    "load_config",
    "plant_has_effects",
    "register",
    "run_label",
    "schema_of",
    "sweep_settings",
    "validate",
]

# Registered on import, as Hydra compositions (the commands', and anyone's with Hydra's own
# compose) expect. Storing a schema builds its defaults, all plain data: importing hds.config
# imports no JAX (the checks import what they need when a config is validated).
register()
