"""How every command answers a user's mistake: one line on stderr, exit status 1 (docs/cli.md).

A mistake the user can fix (a bad value, a missing or malformed file, a directory that cannot
be written, a full disk) raises ValueError or OSError with a message that names the key or file
and the fix. `one_line_errors()` turns it into `error: <message>` on one line; `--debug` on
the command line, or HYDRA_FULL_ERROR=1, shows the traceback instead. Any other exception is a
bug and keeps its traceback. This module knows no domain: the commands bring their own keys.

The commands that act on a finished run (hds.evaluate, hds.export, hds.report) read their
`key=value` arguments with `parse`, in the syntax of the Hydra overrides of the others.
"""

from __future__ import annotations

import contextlib
import errno
import os
import sys
from typing import NoReturn

# errors whose message says all a user needs (OSError: FileNotFoundError, PermissionError,
# a full disk, ...; OverflowError: a number too large for the arrays it goes into)
USER_ERRORS = (ValueError, OSError, FloatingPointError, OverflowError)
DEBUG_FLAG = "--debug"


def debug() -> bool:
    """Whether the user asked for tracebacks (`--debug`, or Hydra's own HYDRA_FULL_ERROR=1)."""
    return os.environ.get("HYDRA_FULL_ERROR") == "1"


def take_debug_flag(argv: list[str]) -> list[str]:
    """`argv` without `--debug`; with it, tracebacks are shown (HYDRA_FULL_ERROR=1, which
    Hydra's own errors honour too, and which the jobs of a multirun inherit)."""
    if DEBUG_FLAG in argv:
        os.environ["HYDRA_FULL_ERROR"] = "1"
    return [a for a in argv if a != DEBUG_FLAG]


def strip_debug_flag() -> None:
    """`take_debug_flag` on sys.argv, before Hydra's parser (which would refuse the flag)."""
    sys.argv[1:] = take_debug_flag(sys.argv[1:])


def describe(err: BaseException) -> str:
    """The one line a user error prints. An OSError's own text lacks the fix (and sometimes
    the file): they are added here, by what went wrong."""
    if isinstance(err, OSError) and not isinstance(err, FileNotFoundError) and err.errno:
        where = f"{err.filename}: " if err.filename else ""
        fix = {
            errno.ENOSPC: "free space on that disk (or write elsewhere) and run the same command "
            "again: a run resumes from its last checkpoint",
            errno.EDQUOT: "free space within your quota and run the same command again",
            errno.EACCES: "choose a directory you can write to, or fix its permissions",
            errno.EPERM: "choose a directory you can write to, or fix its permissions",
            errno.EROFS: "choose a directory on a writable file system",
            errno.EISDIR: "give a file, not a directory",
            errno.ENOTDIR: "a part of the path is a file, not a directory: fix the path",
        }.get(err.errno, "check the path and the disk")
        text = f"{where}{err.strerror or err}: {fix}"
    else:
        text = str(err) or type(err).__name__
    return " ".join(text.split())  # one line, whatever the message held


def fail(message: str) -> NoReturn:
    """Print `error: <message>` as one line on stderr and exit with status 1."""
    print(f"error: {' '.join(message.split())}", file=sys.stderr, flush=True)
    sys.exit(1)


def exit_if_user_error(err: BaseException) -> None:
    """A user error (`USER_ERRORS`) ends the program with its one line, unless `debug()`;
    for anything else, return (for the caller to re-raise, with its traceback)."""
    if isinstance(err, USER_ERRORS) and not debug():
        fail(describe(err))


@contextlib.contextmanager
def one_line_errors():
    """`exit_if_user_error` for what is raised inside."""
    try:
        yield
    except Exception as err:
        exit_if_user_error(err)
        raise


def run(main, argv: list[str] | None = None):
    """main(argv) with `--debug` taken out and user errors as one line (argv: sys.argv[1:])."""
    argv = take_debug_flag(sys.argv[1:] if argv is None else list(argv))
    with one_line_errors():
        return main(argv)


def boolean(text: str) -> bool:
    if text.lower() not in ("true", "false"):
        raise ValueError(text)
    return text.lower() == "true"


def parse(
    argv: list[str],
    keys: dict[str, type],
    prog: str,
    passthrough: tuple[str, ...] = (),
    required: tuple[str, ...] = ("run",),
):
    """(values of `keys` given, with their types; the arguments starting with a `passthrough`
    prefix, as given). Anything else, or a `required` key of `keys` left out, raises a
    ValueError naming what is allowed."""
    usage = f"usage: python -m {prog} " + " ".join(f"{k}=..." for k in keys)
    values, rest = {}, []
    for arg in argv:
        key, sep, value = arg.partition("=")
        if arg in ("-h", "--help"):
            print(usage)
            sys.exit(0)
        if not sep:
            raise ValueError(f"'{arg}' is not key=value; {usage}")
        if key.split(".")[0] in passthrough:
            rest.append(arg)
        elif key in keys:
            try:
                values[key] = keys[key](value)
            except ValueError:
                kind = {"boolean": "true or false"}.get(keys[key].__name__, keys[key].__name__)
                raise ValueError(f"{key}={value!r} must be a {kind}") from None
        else:
            allowed = [*keys, *(f"{p}..." for p in passthrough)]
            raise ValueError(f"unknown key '{key}'; the keys are {', '.join(allowed)}")
    for key in required:
        if key in keys and key not in values:
            raise ValueError(f"{key}=... is required; {usage}")
    return values, rest
