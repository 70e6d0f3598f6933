"""A warm process's phases in CPU seconds: `bench.worker train` on the reference configuration,
every phase the worker times measured with time.process_time (this process's CPU seconds, all
threads) instead of wall seconds, which a loaded machine inflates. Run it from a checkout's
root, twice on the same cache (the first fills it):

    PYTHONPATH=$PWD python experiments/test_suite_time/warm_phases.py /tmp/cache analytic

Prints the worker's phases (imports after the interpreter's start, compose + env + trainer
build, init, trace, XLA compile, run) and the process's CPU seconds until the worker ends.
"""

from __future__ import annotations

import json
import runpy
import sys
import tempfile
import time
from pathlib import Path

time.perf_counter = time.process_time  # the worker's timers, in CPU seconds

from bench.common import REFERENCE  # noqa: E402

cache, backend = sys.argv[1], sys.argv[2]
spec = {
    "overrides": [*REFERENCE, f"env.backend={backend}"],
    "program": "chunk",
    "run": True,
    "cache": cache,
}
with tempfile.TemporaryDirectory() as tmp:
    out = Path(tmp) / "out.json"
    sys.argv = ["bench.worker", "train", json.dumps(spec), str(out)]
    runpy.run_module("bench.worker", run_name="__main__")
    result = json.loads(out.read_text())
phases = {k: round(v, 3) for k, v in result.items() if k.endswith("_s") and isinstance(v, float)}
print(json.dumps({**phases, "process_cpu_s": round(time.process_time(), 3)}))
