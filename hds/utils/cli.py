"""`key=value` command lines of the tools that act on a finished run (hds.evaluate, hds.export)."""

from __future__ import annotations

import sys
import types


def boolean(text: str) -> bool:
    if text.lower() not in ("true", "false"):
        raise ValueError(text)
    return text.lower() == "true"


def parse(argv: list[str], keys: dict[str, type], prog: str, passthrough: tuple[str, ...] = ()):
    """(values of `keys` given, with their types; the arguments starting with a `passthrough`
    prefix, as given). Anything else ends the program with one line naming what is allowed."""
    usage = f"usage: python -m {prog} " + " ".join(f"{k}=..." for k in keys)
    values, rest = {}, []
    for arg in argv:
        key, sep, value = arg.partition("=")
        if arg in ("-h", "--help"):
            sys.exit(usage)
        if not sep:
            sys.exit(f"error: '{arg}' is not key=value; {usage}")
        if key.split(".")[0] in passthrough:
            rest.append(arg)
        elif key in keys:
            try:
                values[key] = keys[key](value)
            except ValueError:
                kind = {"boolean": "true or false"}.get(keys[key].__name__, keys[key].__name__)
                sys.exit(f"error: {key}={value!r} must be a {kind}")
        else:
            allowed = [*keys, *(f"{p}..." for p in passthrough)]
            sys.exit(f"error: unknown key '{key}'; the keys are {', '.join(allowed)}")
    if "run" in keys and "run" not in values:
        sys.exit(f"error: run=<run directory> is required; {usage}")
    return values, rest


def one_line_errors(main, argv: list[str]):
    """main(argv), with what the user can fix (a wrong directory, seed, key) as one line."""
    try:
        return main(argv)
    except (ValueError, FileNotFoundError) as err:
        sys.exit(f"error: {err}")


def check_command_line(argv: list[str], config_name: str = "config") -> None:
    """Unknown keys in a Hydra command line's overrides (hds.run, hds.loop, hds.discover): one
    line naming the keys allowed there, before Hydra composes anything."""
    from hds.config import Config, check_override_keys, cli_overrides, config_groups

    schema = Config
    if config_name == "discover":
        from hds.discover.config import DiscoverAppConfig

        schema = DiscoverAppConfig
    try:
        check_override_keys(cli_overrides(argv), schema, config_groups())
    except ValueError as err:
        sys.exit(f"error: {err}")


def callable_module(name: str, function) -> None:
    """Make the command's module `name` callable as `function`: `hds.evaluate(...)` and
    `hds.export(...)` are the API's functions, and importing the command's module of the same
    name (which makes it the package's attribute) must not turn them into a module."""

    class CommandModule(types.ModuleType):
        def __call__(self, *args, **kwargs):
            return function()(*args, **kwargs)

    sys.modules[name].__class__ = CommandModule
