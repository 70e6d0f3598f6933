"""`make test-slurm`: sweeps through `hydra/launcher=slurm` on a real (single-node) SLURM cluster
(tests/slurm/up.sh brings it up). Not a pytest file: `make test` never needs a scheduler.

1. The main experiment as a two-job multirun (closed-loop PODS and the oracle, debug=fast
   budgets), one of its array tasks cancelled with `scancel`: the sweep exits non-zero, the
   other job's results stay; the same sweep started again reruns only the cancelled job and
   ends with the sweep's story (hds.story) and summary.json of both jobs.
2. A sweep one of whose jobs fails (its MJCF is missing): exit code 1, the failed job named.
3. `python -m hds.loop` through the launcher: one correction round on the cluster, gap
   discovery naming the rail's friction beside the plant's 20 N.

python tests/slurm/check.py [OUT]  (OUT: default a fresh directory under /tmp)
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SLURM = (
    "hydra/launcher=slurm",
    "hydra.launcher.partition=debug",
    "hydra.launcher.cpus_per_task=1",
    "hydra.launcher.mem_gb=1",
    "hydra.launcher.gpus_per_node=null",
    "hydra.launcher.timeout_min=30",
)
TINY = ("+experiment=sim2real_friction", "debug=fast", "seeds=2", "logger=none")
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "WANDB_MODE": "offline"}


def hds(module: str, *args: str, log: Path) -> subprocess.Popen:
    """`python -m hds.<module> -m ...` on the cluster, its output into `log`."""
    out = open(log, "w")  # noqa: SIM115 (closed with the process, below)
    cmd = [sys.executable, "-m", f"hds.{module}", "-m", *args, *SLURM]
    print("$", " ".join(cmd[1:]), flush=True)
    return subprocess.Popen(cmd, cwd=ROOT, env=ENV, stdout=out, stderr=subprocess.STDOUT)


def finish(proc: subprocess.Popen, log: Path, timeout: float = 1200) -> tuple[int, str]:
    rc = proc.wait(timeout=timeout)
    return rc, log.read_text()


def array_tasks(sweep: Path) -> list[str]:
    """The SLURM ids (<array>_<task>) submitit submitted for a sweep, from its folders."""
    return sorted(p.name for p in (sweep / ".submitit").glob("*_*") if p.is_dir())


def slurm_state(job: str) -> str:
    out = subprocess.run(
        ["sacct", "-n", "-X", "-P", "-o", "State", "-j", job], capture_output=True, text=True
    )
    return out.stdout.strip().split("\n")[0].split()[0] if out.stdout.strip() else ""


def check(condition: bool, message: str, log: str = "") -> None:
    if not condition:
        sys.exit(f"FAILED: {message}\n--- last output ---\n{log[-4000:]}")
    print(f"ok: {message}", flush=True)


def cancelled_then_resumed(out: Path) -> None:
    sweep = out / "sweep"
    args = (*TINY, "method=pods_cl,oracle", f"hydra.sweep.dir={sweep}")
    proc = hds("run", *args, log=out / "sweep_first.log")
    deadline = time.monotonic() + 300
    while len(array_tasks(sweep)) < 2:  # submitit writes a folder per array task
        if proc.poll() is not None or time.monotonic() > deadline:
            check(
                False,
                "two array tasks submitted within 300 s",
                (out / "sweep_first.log").read_text(),
            )
        time.sleep(0.5)
    cancelled = array_tasks(sweep)[1]
    # cancelled while still pending, an array task shows in sacct only as <array>_[<task>],
    # which submitit never matches: the sweep would wait forever. Cancel it once it runs.
    while slurm_state(cancelled) != "RUNNING":
        if proc.poll() is not None or time.monotonic() > deadline:
            check(False, f"{cancelled} started within 300 s", (out / "sweep_first.log").read_text())
        time.sleep(0.5)
    subprocess.run(["scancel", cancelled], check=True)
    print(f"scancel {cancelled}", flush=True)
    rc, text = finish(proc, out / "sweep_first.log")
    check(rc != 0, f"a sweep with a cancelled job exits non-zero (rc {rc})", text)
    check(slurm_state(cancelled) == "CANCELLED", f"sacct says {cancelled} was cancelled", text)
    check((sweep / "0" / "summary.json").is_file(), "the other job finished", text)
    check(not (sweep / "1" / "summary.json").exists(), "the cancelled job has no result", text)
    before = (sweep / "0" / "summary.json").stat().st_mtime_ns

    rc, text = finish(hds("run", *args, log=out / "sweep_second.log"), out / "sweep_second.log")
    check(rc == 0, "the same sweep started again finishes", text)
    check(
        (sweep / "0" / "summary.json").stat().st_mtime_ns == before,
        "the finished job was not trained again",
        text,
    )
    logs = "".join(p.read_text() for p in (sweep / ".submitit").glob("*/*_log.*"))
    check("is finished (summary.json exists): skipped" in logs, "its job said it skipped", text)
    summary = json.loads((sweep / "summary.json").read_text())
    check(
        {r["job"] for r in summary["rows"]} == {"0", "1"} and not summary["failed_jobs"],
        "summary.json gathers both jobs' rows",
        text,
    )
    for line in (
        "sim2real_friction: 2 jobs in",
        "On the plant coulomb_friction@slider: best",
        "pods_cl (2 seeds)",
        "oracle (2 seeds)",
        "x the oracle's",
        f"figure: {sweep / 'plots' / 'summary.png'}",
    ):
        check(line in text, f"the sweep's story says {line!r}", text)
    check((sweep / "plots" / "summary.png").is_file(), "the story's figure was written", text)


def failed_job_exit_code(out: Path) -> None:
    sweep = out / "failed"
    missing = out / "missing.xml"
    args = (*TINY, "method=pods_cl", f"env.xml=cartpole.xml,{missing}", f"hydra.sweep.dir={sweep}")
    rc, text = finish(hds("run", *args, log=out / "failed.log"), out / "failed.log")
    check(rc == 1, f"a sweep with a failed job exits 1 (rc {rc})", text)
    check("error: 1 of 2 jobs failed: 1 (see their failed.txt)" in text, "it names the job", text)
    check((sweep / "1" / "failed.txt").is_file(), "the failed job wrote failed.txt", text)
    check((sweep / "0" / "summary.json").is_file(), "the other job's result stays", text)


def loop_round(out: Path) -> None:
    sweep = out / "loop"
    args = (*TINY, "method=pods_cl_effects", "loop.rounds=1", f"hydra.sweep.dir={sweep}")
    rc, text = finish(hds("loop", *args, log=out / "loop.log"), out / "loop.log")
    check(rc == 0, "a hds.loop round runs on the cluster", text)
    rounds = json.loads((sweep / "0" / "loop.json").read_text())["rounds"]
    check([r["round"] for r in rounds] == [0, 1], "round 0 and one correction round", text)
    named = [(e["name"], e["target"]) for e in rounds[1]["effects"]]
    check(
        ("coulomb_friction", "slider") in named, f"round 1 named the rail friction: {named}", text
    )
    check("discovery named coulomb_friction@slider force" in text, "the story tells it", text)
    check("(plant: 20)" in text, "beside the plant's 20 N", text)


def main() -> None:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp(prefix="hds-slurm-"))
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    print(f"make test-slurm: outputs in {out}", flush=True)
    cancelled_then_resumed(out)
    failed_job_exit_code(out)
    loop_round(out)
    print(f"make test-slurm: every check passed in {time.monotonic() - started:.0f} s")


if __name__ == "__main__":
    main()
