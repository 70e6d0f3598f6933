"""The commands hds installs (`[project.scripts]`: hds-run, hds-loop, hds-discover,
hds-evaluate, hds-export, hds-report, hds-dynamics), and what the Hydra commands (hds.run,
hds.loop, hds.discover) check before Hydra composes anything (docs/cli.md).

The Hydra commands (hds-run, hds-loop, hds-discover) call their module's checks and `main` in
this process, so that Hydra's tab completion knows the script's name. The others run their
module as `python -m` does (runpy, as `__main__`): no such module imported under its package
name, where it would hide the deprecated API alias of the same name (`hds.evaluate`, now
`hds.evaluate_policy`; `hds.export`, now `hds.export_policy`).
"""

from __future__ import annotations

import importlib
import itertools
import runpy
import sys

from hds.utils import cli

SCRIPTS = {  # script: the module it runs
    "hds-run": "hds.run",
    "hds-loop": "hds.loop",
    "hds-discover": "hds.discover",
    "hds-evaluate": "hds.evaluate",
    "hds-export": "hds.export",
    "hds-report": "hds.report",
    "hds-dynamics": "hds.dynamics",
}


def _run_module(name: str) -> None:
    runpy.run_module(name, run_name="__main__", alter_sys=True)


def _hydra_command(name: str, config_name: str = "config") -> None:
    """A Hydra command called in this process, not through runpy: runpy sets sys.argv[0] to
    the module's file, and Hydra's tab completion then completes `python` instead of the
    script's own name (`eval "$(hds-run -sc install=bash)"`). No API name of hds is one of
    these modules' names, so importing them hides nothing."""
    command = importlib.import_module(name)
    before_hydra(config_name, loop=name == "hds.loop")
    command.main()


def run() -> None:
    _hydra_command("hds.run")


def loop() -> None:
    _hydra_command("hds.loop")


def discover() -> None:
    _hydra_command("hds.discover.__main__", "discover")


def evaluate() -> None:
    _run_module("hds.evaluate")


def export() -> None:
    _run_module("hds.export")


def report() -> None:
    _run_module("hds.report")


def dynamics() -> None:
    _run_module("hds.dynamics")


def before_hydra(config_name: str = "config", loop: bool = False) -> None:
    """What a Hydra command does before handing sys.argv to Hydra: take out `--debug`, then
    refuse unknown keys and every invalid job (a single run: its configuration; a multirun:
    each job's, its data's size included, one line each), before Hydra composes anything or
    launches a job. `loop`: the command is hds.loop (the data it records are the loop's)."""
    cli.strip_debug_flag()
    argv = sys.argv[1:]
    if INFO_FLAGS & set(argv) or cli.debug():
        return  # Hydra's help and printouts need no valid config; --debug: Hydra's traceback
    with cli.one_line_errors():
        check_command_line(argv, config_name)
    if bad := invalid_jobs(argv, config_name, loop):
        for line in bad:
            print(f"error: {line}", file=sys.stderr)
        sys.exit(1)


INFO_FLAGS = {
    "-h",
    "--help",
    "--hydra-help",
    "-i",
    "--info",
    "-c",
    "--cfg",
    "--shell-completion",
    "-sc",
}


def check_command_line(argv: list[str], config_name: str = "config") -> None:
    """Unknown keys in a Hydra command line's overrides: a ValueError naming the keys allowed
    there, before Hydra composes anything."""
    from hds.config import check_override_keys, cli_overrides, config_groups, schema_of

    check_override_keys(cli_overrides(argv), schema_of(config_name), config_groups())


def invalid_jobs(argv: list[str], config_name: str = "config", loop: bool = False) -> list[str]:
    """One line per job whose configuration is refused (Hydra's composition errors, an unknown
    option of a group or a value of the wrong type, included), naming a multirun's job by its
    swept values: a sweep with a bad value launches no job at all. A multirun's jobs are also
    refused for data past their limits (hds.data.budget; a single run checks its own, once).
    The config's own sweeps (`hydra.sweeper.params`) count as the command line's do; a key
    the basic sweeper does not expand (an optimizing sweeper's interval) is left to each
    job."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    from hds.config import Config, cli_overrides, compose, sweep_settings
    from hds.data.budget import check_planned

    config_name = _flag_value(argv, ("--config-name", "-cn")) or config_name
    config_dir = _flag_value(argv, ("--config-dir", "-cd"))
    overrides = OverridesParser.create().parse_overrides(cli_overrides(argv))
    single = [o.input_line for o in overrides if not o.is_sweep_override()]
    dirs = [config_dir] if config_dir else []
    try:
        settings = sweep_settings(single, config_name, dirs)
    except (*cli.USER_ERRORS, HydraException) as err:
        return [cli.describe(err)]
    # -m, or an experiment that makes itself a multirun (hydra.mode: MULTIRUN)
    multirun = bool({"-m", "--multirun"} & set(argv)) or settings.multirun
    if multirun:
        # the sweeper crosses the config's own sweeps (hydra.sweeper.params) with the command
        # line's, a key on the command line replacing the config's: check the jobs it launches
        lines = [f"{key}={values}" for key, values in settings.params.items()]
        overrides = OverridesParser.create().parse_overrides(lines) + overrides
    chosen = {}  # as Hydra's basic sweeper: the last override of a key, in its first place
    for override in overrides:
        chosen[override.get_key_element()] = override
    fixed, swept = [], []
    for key, override in chosen.items():
        if override.key_or_group.startswith("hydra"):
            continue  # Hydra's own settings: no job's configuration
        if override.is_sweep_override() and not multirun:
            return [
                f"{override.input_line} sweeps several values: add -m (a multirun), or give "
                f"one value (a list is written in brackets: {key}=[...])"
            ]
        if not override.is_sweep_override():
            fixed.append(f"{key}={override.get_value_element_as_str()}")
            continue
        try:
            values = list(override.sweep_string_iterator())
        except Exception:  # an interval: the optimizing sweeper draws it, each job checks it
            continue
        swept.append([f"{key}={v}" for v in values])
    jobs = list(itertools.product(*swept))
    lines = []
    for number, job in enumerate(jobs):
        try:
            # a sweep's jobs may run elsewhere (joblib's processes, SLURM's nodes): each checks
            # its memory where it runs, and this process keeps off the device (a GPU's memory)
            cfg = compose(
                [*fixed, *job],
                config_name,
                check_memory=not multirun,
                config_dirs=dirs,
            )
            if multirun and type(cfg) is Config:  # hds.discover checks its data as it loads it
                check_planned(cfg, loop)
        except (*cli.USER_ERRORS, HydraException) as err:
            named = f"job {number} ({' '.join(job)}): " if multirun else ""
            lines.append(named + cli.describe(err))
    if lines and multirun:
        lines.append(f"{len(lines)} of {len(jobs)} jobs refused, none launched: fix the values")
    return lines


def _flag_value(argv: list[str], names: tuple[str, ...]) -> str | None:
    """The value of a Hydra flag (`--config-name NAME`, `--config-name=NAME`, its short form)."""
    for i, arg in enumerate(argv):
        if arg in names and i + 1 < len(argv):
            return argv[i + 1]
        flag, eq, value = arg.partition("=")
        if eq and flag in names:
            return value
    return None
