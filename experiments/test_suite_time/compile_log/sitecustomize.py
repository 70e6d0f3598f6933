"""Every XLA compile of every Python process, one JSON line each (issue 43, sixth pass).

Off unless `HDS_COMPILE_LOG` names a file and this directory is on PYTHONPATH (measure.py
puts it there): then each process (pytest's and every `python -m hds.*` a test starts, which
inherit both) appends to that file, per backend compile, the program's name, its seconds
(jax.monitoring's `/jax/core/compile/backend_compile_duration`, whose `fun_name` names it),
the persistent compilation cache's key (a hash of the lowered module, the compile options and
the versions: the same key is the same program, shapes included; read from jax's own DEBUG
line of the cache's hit or miss, the only public place it appears), whether that was a hit,
and the test running (pytest's PYTEST_CURRENT_TEST, which the runs a test starts inherit);
per trace and lowering the name and seconds; and per process at exit its CPU seconds.
jax is not imported here: the listener is registered when the process itself imports
jax.monitoring, so a process that never uses jax pays nothing."""

from __future__ import annotations

import importlib.abc
import importlib.util
import json
import os
import re
import sys
import threading

_PATH = os.environ.get("HDS_COMPILE_LOG")

if _PATH:
    import atexit
    import logging
    import resource

    _last_key = threading.local()
    _lock = threading.Lock()
    _EVENTS = {
        "/jax/core/compile/backend_compile_duration": "compile",
        "/jax/core/compile/jaxpr_trace_duration": "trace",
        "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
    }
    _CACHE_LINE = re.compile(
        r"(Persistent compilation cache hit|PERSISTENT COMPILATION CACHE MISS)"
    )

    def _write(row: dict) -> None:
        row["pid"] = os.getpid()
        row["test"] = os.environ.get("PYTEST_CURRENT_TEST", "").rsplit(" (", 1)[0]
        line = json.dumps(row) + "\n"
        with _lock, open(_PATH, "a") as f:
            f.write(line)

    class _CacheKeys(logging.Handler):
        """jax's DEBUG line of each persistent-cache lookup: its key, for the compile after it."""

        def emit(self, record):
            if _CACHE_LINE.match(str(record.msg)) and len(record.args) == 2:
                _last_key.value = (record.args[1], record.msg.startswith("Persistent"))

    class _Forward(logging.Filter):
        # the logger's DEBUG lines are turned on for the handler above only: what it logged
        # before (INFO and up) still reaches the handlers above it
        def filter(self, record):
            if record.levelno >= logging.INFO and record.levelno > logging.root.manager.disable:
                logging.getLogger("jax").handle(record)
            return True

    _compiler_log = logging.getLogger("jax._src.compiler")
    _compiler_log.setLevel(logging.DEBUG)
    _compiler_log.propagate = False
    # hds.utils.quiet (brax's System build) turns logging off below WARNING for a while, which
    # would hide the keys of the compiles inside it: this logger asks no one
    _compiler_log.isEnabledFor = lambda level: True
    _handler = _CacheKeys(logging.DEBUG)
    _handler.addFilter(_Forward())
    _compiler_log.addHandler(_handler)

    def _listener(event, duration, **kwargs):
        kind = _EVENTS.get(event)
        if kind is None:
            return
        row = {"kind": kind, "name": str(kwargs.get("fun_name", "")), "s": round(duration, 4)}
        if kind == "compile":
            key, hit = getattr(_last_key, "value", (None, False))
            _last_key.value = (None, False)
            row.update(key=key, hit=hit)
        _write(row)

    def _at_exit():
        usage = resource.getrusage(resource.RUSAGE_SELF)
        _write(
            {
                "kind": "process",
                "argv": " ".join(sys.argv)[:200],
                "cpu": round(usage.ru_utime + usage.ru_stime, 2),
            }
        )

    atexit.register(_at_exit)

    class _AfterMonitoring(importlib.abc.MetaPathFinder):
        """Registers the listener once jax.monitoring is imported (by the process itself)."""

        def find_spec(self, name, path, target=None):
            if name != "jax.monitoring":
                return None
            sys.meta_path.remove(self)
            spec = importlib.util.find_spec(name)
            run = spec.loader.exec_module

            def exec_module(module):
                run(module)
                module.register_event_duration_secs_listener(_listener)

            spec.loader.exec_module = exec_module
            return spec

    sys.meta_path.insert(0, _AfterMonitoring())
