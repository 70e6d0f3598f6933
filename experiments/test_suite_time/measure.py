"""Each test file alone from an empty compilation cache, every compile logged (sixth pass).

    PYTHONPATH=$PWD python experiments/test_suite_time/measure.py OUT [test_x.py ...]

runs, per file (default: every tests/test_*.py), `nice -n 10 python -m pytest -q -n 0 -m
"not slow" tests/<file>` with a fresh HDS_JAX_CACHE and compile_log/ on PYTHONPATH, so every
process (pytest's and the runs its tests start) appends its compiles to OUT/<file>.jsonl
(compile_log/sitecustomize.py); OUT/<file>.time holds `/usr/bin/time`'s wall, user and sys
seconds and the load average before and after. `report.py OUT` makes the tables.

`--shared` (seventh pass) keeps one cache for every file named, in the order given, emptied
only at the start: a program an earlier file compiled is a hit in a later one, as in `make
test`'s shared cache (where a pytest process keeps only its compiles of 0.5 s and more)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent


def main(out: str, *files: str) -> None:
    shared = "--shared" in files
    files = tuple(f for f in files if f != "--shared")
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = files or sorted(p.name for p in (ROOT / "tests").glob("test_*.py"))
    if shared:
        shutil.rmtree(out_dir / "cache", ignore_errors=True)
    for name in names:
        log, timing = out_dir / f"{name}.jsonl", out_dir / f"{name}.time"
        if timing.exists() and "result" in timing.read_text():  # resumable: a file measured is kept
            continue
        log.unlink(missing_ok=True)
        # one path for every file, emptied before each: jax's cache keys hash the cache's
        # directory too (its compile options name it), so only keys made under one path compare
        cache = out_dir / "cache"
        if not shared:
            shutil.rmtree(cache, ignore_errors=True)
        env = dict(
            os.environ,
            HDS_JAX_CACHE=str(cache),
            HDS_COMPILE_LOG=str(log),
            PYTHONPATH=os.pathsep.join([str(HERE / "compile_log"), str(ROOT)]),
        )
        load0 = os.getloadavg()[0]
        cmd = ["nice", "-n", "10", "/usr/bin/time", "-f", "%e %U %S", "-o", str(timing)]
        cmd += [sys.executable, "-m", "pytest", "-q", "-n", "0", "-m", "not slow"]
        cmd += ["-p", "no:cacheprovider", f"tests/{name}"]
        done = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        tail = done.stdout.strip().splitlines()[-1:] or [""]
        with timing.open("a") as f:
            f.write(f"load {load0:.2f} {os.getloadavg()[0]:.2f}\nresult {tail[0]}\n")
        print(name, timing.read_text().replace("\n", " | "), flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
