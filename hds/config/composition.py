"""Composing and loading configs: `compose(overrides)` as the commands compose theirs (Hydra,
from hds/conf), `load_config` from a run directory's config.yaml, `env_config` from a plain
dict, and the overrides of a command line. Every result is validated (hds.config.validation).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import NamedTuple

from omegaconf import DictConfig, OmegaConf

from hds.config.schemas import Config, DiscoverAppConfig, EnvConfig
from hds.config.validation import check_override_keys, validate

log = logging.getLogger("hds.config")


def cli_overrides(argv: list[str]) -> list[str]:
    """The overrides of a Hydra command line (what is not a flag nor a flag's value)."""
    with_value = {"--config-dir", "-cd", "--config-name", "-cn", "--config-path", "-cp"}
    with_value |= {"--cfg", "-c", "--package", "-p"}  # --cfg job|hydra|all: what to print
    with_value |= {"--shell-completion", "-sc"}  # install=bash, query=bash: not overrides
    out, skip = [], False
    for arg in argv:
        if skip or arg.startswith("-"):
            skip = arg in with_value
            continue
        out.append(arg)
    return out


CONF_DIR = Path(__file__).resolve().parents[1] / "conf"  # hds/conf, package data


def config_groups() -> list[str]:
    """The config groups of conf/ (env, algo, method, ...): keys of an override too."""
    return sorted(p.name for p in CONF_DIR.iterdir() if p.is_dir() and p.name != "hydra")


def schema_of(config_name: str) -> type:
    """The schema of a top-level config: hds.discover's ("discover") or the others' (Config)."""
    return DiscoverAppConfig if config_name == "discover" else Config


def compose(overrides=(), config_name: str = "config", check_memory: bool = True, config_dirs=()):
    """The validated config of `python -m hds.run <overrides>` (config_name="config") or of
    `python -m hds.discover <overrides>` ("discover"), composed without the command line:

        cfg = hds.compose(["method=pods_cl", "seeds=3", "env.backend=analytic"])

    config_dirs: further folders searched for config options, as `--config-dir` adds them
    (a study's experiments beside the study)."""
    composed = _hydra_compose(overrides, config_name, config_dirs, checked=True)
    return validate(composed, check_memory)


def _hydra_compose(
    overrides, config_name: str, config_dirs, with_hydra: bool = False, checked: bool = False
):
    """Hydra's composition from hds/conf, with `config_dirs` on its search path (as
    `--config-dir` adds them); `with_hydra`: Hydra's own node (`hydra.*`) too; `checked`:
    the overrides' keys checked against the schema first (`check_override_keys`), which an
    entry of the cache below passed when it was kept (the check reads only what its key
    holds: the overrides, the schema and hds/conf's groups).

    The job's composition (without Hydra's node, whose run directory and time are the
    process's own) is kept in the program cache (hds.utils.runtime.cached_build; off where
    the program cache is off): ~0.3 s of a second process of a configuration, 63 config reads
    and merges. Its key is everything Hydra composes from: the config name, the overrides,
    hds/conf (every hds file, `content_key`), the `config_dirs`' YAML files, Hydra's and
    OmegaConf's versions, the installed Hydra plugins' files and Hydra's ConfigStore as it is
    now; interpolations stay unresolved (`${oc.env:...}` is read when the config is)."""
    if with_hydra:
        return _compose_now(overrides, config_name, config_dirs, with_hydra)
    from hds.utils.runtime import cached_build

    def build():
        if checked:
            check_override_keys(overrides, schema_of(config_name), config_groups())
        return _compose_now(overrides, config_name, config_dirs)

    return cached_build(
        "composed_config",
        build,
        checked,
        config_name,
        [str(o) for o in overrides],
        [_yaml_files(d) for d in config_dirs],
        _hydra_state(),
    )


def _yaml_files(directory) -> tuple:
    """A config folder as Hydra reads it: its path and its YAML files' names and contents."""
    root = Path(directory).resolve()
    files = sorted(p for p in root.rglob("*") if p.suffix in (".yaml", ".yml") and p.is_file())
    return str(root), [(str(p.relative_to(root)), p.read_bytes()) for p in files]


def _hydra_state() -> tuple:
    """What Hydra composes from besides the config folders: its and OmegaConf's versions, the
    files of the installed Hydra plugins (their configs and search-path additions) and the
    ConfigStore's entries (pickled: every node's values, whoever stored them)."""
    import pickle

    import hydra
    import omegaconf
    from hydra.core.config_store import ConfigStore

    try:
        import hydra_plugins

        roots = list(hydra_plugins.__path__)
    except ImportError:  # no plugin installed
        roots = []
    plugins = [
        (str(p.relative_to(root)), p.read_bytes())
        for root in map(Path, roots)
        for p in sorted(root.rglob("*"))
        if p.is_file() and "__pycache__" not in p.parts
    ]
    # the store's `hydra` group (launchers, sweepers) is Hydra's and its plugins' (their
    # versions and files are in the key), and it fills when the first composition discovers
    # the plugins: every other entry (hds's schemas, a user's) by its values
    repo = ConfigStore.instance().repo
    store = pickle.dumps({k: v for k, v in repo.items() if k != "hydra"})
    return hydra.__version__, omegaconf.__version__, plugins, store


def _compose_now(overrides, config_name: str, config_dirs, with_hydra: bool = False):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    search = [f"file://{Path(d).resolve()}" for d in config_dirs]
    extra = [f"hydra.searchpath=[{','.join(search)}]"] if search else []
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return hydra_compose(
            config_name, overrides=[*extra, *overrides], return_hydra_config=with_hydra
        )


class SweepSettings(NamedTuple):
    """What a composed config asks of Hydra's sweeper itself."""

    multirun: bool  # hydra.mode: MULTIRUN (as +experiment=optuna sets it): a sweep needs no -m
    params: dict[str, str]  # hydra.sweeper.params: key -> values in Hydra's override grammar


def sweep_settings(overrides=(), config_name: str = "config", config_dirs=()) -> SweepSettings:
    """Whether the config that `overrides` (none of them a sweep) compose is a multirun by
    itself, and the sweeps it sets its sweeper (`0,1,2`, `choice(a,b)`, an interval), from one
    composition with Hydra's node, kept in the program cache as the job's composition is (a
    single run asks it too; its key: everything Hydra composes from)."""

    def build():
        composed = _compose_now(overrides, config_name, config_dirs, with_hydra=True)
        params = OmegaConf.select(composed, "hydra.sweeper.params", default=None)
        return SweepSettings(
            str(composed.hydra.mode).endswith("MULTIRUN"),
            {str(k): str(v) for k, v in (params or {}).items()},
        )

    from hds.utils.runtime import cached_build

    return cached_build(
        "sweep_settings",
        build,
        config_name,
        [str(o) for o in overrides],
        [_yaml_files(d) for d in config_dirs],
        _hydra_state(),
    )


def env_config(env: dict) -> EnvConfig:
    """A checked EnvConfig from a plain dict (e.g. the env gap discovery corrected)."""
    cfg = OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(EnvConfig), env))
    cfg.check()
    for effect in cfg.effects:
        effect.check()
    return cfg


def load_config(path) -> Config:
    """The validated config of a run from its saved config.yaml. Settings this version of
    hds no longer has (a run directory written by an older one) are dropped with a warning
    naming them, so that its policies stay loadable."""
    schema = OmegaConf.structured(Config)
    saved = OmegaConf.load(path)
    removed = _drop_unknown_keys(saved, schema)
    if removed:
        log.warning(
            "%s: ignored settings this version of hds no longer has: %s", path, ", ".join(removed)
        )
    return validate(OmegaConf.merge(schema, saved))


def _drop_unknown_keys(node, schema, where: str = "") -> list[str]:
    """Remove from `node` (in place) the keys of structured nodes that `schema` lacks;
    returns their dotted paths."""
    if not isinstance(node, DictConfig) or not isinstance(schema, DictConfig):
        return []
    if not dataclasses.is_dataclass(OmegaConf.get_type(schema)):
        return []
    allowed = {f.name for f in dataclasses.fields(OmegaConf.get_type(schema))}
    removed = []
    for key in [str(k) for k in node.keys()]:
        path = f"{where}.{key}" if where else key
        if key not in allowed:
            removed.append(path)
            del node[key]
        elif not OmegaConf.is_missing(schema, key) and not OmegaConf.is_interpolation(node, key):
            removed += _drop_unknown_keys(node[key], schema[key], path)
    return removed
