"""What every section shares: a timer, config composition, the machine's description, the
result files, the subprocess runner, env-step accounting and a fixed-state evaluation."""

from __future__ import annotations

import contextlib
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import hds  # noqa: F401  (quiets XLA's C++ log before jax loads)

os.environ.setdefault("WANDB_MODE", "offline")
os.environ.setdefault("WANDB_SILENT", "true")
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "hds" / "conf"


def result_files(backend: str, folder: Path = ROOT / "bench") -> tuple[Path, Path]:
    """results.json and RESULTS.md of jax's backend: the CPU ones are committed as they are; a
    GPU's go beside them (results-gpu.json, RESULTS-gpu.md), so neither overwrites the other."""
    suffix = "" if backend == "cpu" else f"-{backend}"
    return Path(folder) / f"results{suffix}.json", Path(folder) / f"RESULTS{suffix}.md"


RESULTS_JSON, RESULTS_MD = result_files(jax.default_backend())

# The reference project's notebook configuration (FIELD-NOTES.md), on the project's copy of its
# task (env=cartpole_reference: horizon 100, q and qd uniform in [-5, 5], its reward).
REFERENCE = (
    "env=cartpole_reference",
    "algo.epochs=30",
    "algo.rollouts=50",
    "algo.inner_epochs=20",
    "algo.order=first",
    "algo.step_size=2e-2",
    "algo.learning_rate=1e-3",
)
# The reference implementation measured on this kind of machine (shared/FIELD-NOTES.md).
REFERENCE_IMPL = {
    "pods_train_s": 573.0,
    "pods_final_return": -12858.0,  # 50 rollouts of 100 steps on its training env
    "hds_train_s": 779.0,
    "hds_final_return": -990.0,
    "zero_action_return": -6806.0,
    "source": "shared/FIELD-NOTES.md (reference code on jax 0.9.2, brax 0.14.2, 2-core CPU)",
}


# ---------------------------------------------------------------------------------------- timing
@dataclass
class Timer:
    s: float = float("nan")


@contextlib.contextmanager
def timed():
    """`with timed() as t: ...` then t.s holds the elapsed wall-clock seconds."""
    timer = Timer()
    start = time.perf_counter()
    try:
        yield timer
    finally:
        timer.s = time.perf_counter() - start


def block(tree):
    """Wait for every array of a result, so a timer measures the work and not the dispatch."""
    return jax.block_until_ready(tree)


def best_of(fn, repeats: int) -> tuple[float, list[float]]:
    """Call fn() `repeats` times (it must block); returns (median seconds, all seconds)."""
    times = []
    for _ in range(max(1, repeats)):
        with timed() as t:
            fn()
        times.append(t.s)
    return float(np.median(times)), times


def load_average() -> list[float]:
    """1, 5 and 15 minute load averages: other processes on the machine skew timings."""
    return [round(x, 2) for x in os.getloadavg()]


def peak_rss_mb() -> float:
    """This process's peak resident memory so far, in MiB: VmHWM of /proc/self/status (reset
    at exec; ru_maxrss is not: a child started by a large parent inherits the parent's peak),
    falling back to ru_maxrss (KiB on Linux) where /proc is missing."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# ---------------------------------------------------------------------------------------- config
def compose(*overrides: str):
    """The validated config `python -m hds.run <overrides>` would use."""
    from hds.config import compose as hds_compose

    return hds_compose(list(overrides))


def backend_available(name: str) -> bool:
    from hds.envs.system import BACKENDS

    return name in BACKENDS


def steps_per_epoch(cfg) -> dict:
    """Env steps one PODS/HDS epoch simulates. `samples`: closed-loop policy steps (the data the
    policy is regressed on); `differentiated`: steps of the open-loop rollouts whose gradient is
    taken (forward and backward); `simulated`: every forward step, line-search rollouts included.
    Gauss-Newton's Jacobian (algo.order=second) is not counted; closed-loop improvement
    (algo.improve_in) replays the improved trajectory once more."""
    from hds import anneal

    batch = cfg.algo.rollouts * cfg.env.task.horizon
    candidates = anneal.candidates(cfg.anneal.kind, cfg.algo.line_search)
    steps = cfg.algo.improve_steps
    replay = cfg.algo.improve_in == "closed_loop"
    return {
        "samples": batch,
        "differentiated": batch * steps,
        "simulated": batch * (1 + steps * (1 + candidates) + replay),
        "candidates": candidates,
    }


# --------------------------------------------------------------------------------------- machine
def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gib() -> float | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                return round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    return None


def _version(package: str) -> str | None:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return None


def machine() -> dict:
    return {
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "memory_gib": _memory_gib(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax_backend": jax.default_backend(),
        "devices": [str(d) for d in jax.devices()],
        "accelerators": sorted({d.device_kind for d in jax.devices() if d.platform != "cpu"}),
        "versions": {p: _version(p) for p in ("jax", "jaxlib", "brax", "flax", "optax", "mujoco")},
    }


# ------------------------------------------------------------------------------------ result files
def load_results(path: Path = RESULTS_JSON) -> dict:
    if not path.exists():
        return {"sections": {}}
    from hds.utils.io import read_json

    return read_json(path)


def save_section(
    name: str, data: dict, path: Path = RESULTS_JSON, md: Path = RESULTS_MD, merge=None
) -> dict:
    """Merge one section's result into results.json (others are kept) and re-render RESULTS.md.
    `merge(stored, new)` (a section's own, where a partial rerun should keep the stored rows it
    did not measure again) combines the section's stored result with the new one."""
    from bench.markdown import render
    from hds.utils.io import atomic_write_bytes, atomic_write_json

    results = load_results(path)
    stored = results.get("sections", {}).get(name)
    if merge is not None and stored:
        data = merge(stored, data)
    results.setdefault("sections", {})[name] = {
        **data,
        "measured_at": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "machine": machine(),
    }
    atomic_write_json(path, results)
    results = load_results(path)  # rendered as stored (a NaN is stored as null: "-")
    atomic_write_bytes(md, render(results).encode())
    return results


# ------------------------------------------------------------------------------------- subprocess
def run_worker(kind: str, spec: dict, timeout: float = 1800.0, env: dict | None = None) -> dict:
    """Run `python -m bench.worker kind spec` in a fresh process (fresh compile state, its own
    peak memory); returns the worker's JSON result plus `process_s`, the process's wall time."""
    with tempfile.TemporaryDirectory(prefix="hds-bench-") as tmp:
        out = Path(tmp) / "result.json"
        cmd = [sys.executable, "-m", "bench.worker", kind, json.dumps(spec), str(out)]
        cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
        with timed() as t:
            proc = subprocess.run(
                cmd,
                cwd=ROOT,
                capture_output=True,
                text=True,
                timeout=timeout,
                env={**os.environ, **(env or {})},
            )
        if proc.returncode != 0 or not out.exists():
            tail = (proc.stderr or proc.stdout)[-2000:]
            raise RuntimeError(f"bench.worker {kind} failed (rc {proc.returncode}):\n{tail}")
        result = json.loads(out.read_text())
    result["process_s"] = t.s
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the worker's (it has ended)
    result["process_cpu_s"] = after.ru_utime + after.ru_stime - cpu.ru_utime - cpu.ru_stime
    return result


# ------------------------------------------------------------------------------------- evaluation
class FixedStates:
    """Deterministic returns from fixed initial states: `episodes` states drawn from the task's
    distribution with PRNGKey(seed) (the reference evaluated 50 rollouts of 100 steps from
    PRNGKey(1)). One compiled function per policy kind, reused for every parameter set."""

    def __init__(self, env, episodes: int = 50, seed: int = 1):
        self.env = env
        keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
        self.q0, self.qd0 = jax.vmap(env.task.initial)(keys)
        sim = env.sim
        self.low = jnp.asarray(sim.ctrl_range[:, 0])
        self.high = jnp.asarray(sim.ctrl_range[:, 1])
        self._compiled: dict = {}

    def returns(self, apply, params) -> np.ndarray:
        """Returns [episodes] of the policy u = apply(params, obs)."""
        if apply not in self._compiled:
            self._compiled[apply] = jax.jit(self._returns_fn(apply))
        return np.asarray(self._compiled[apply](params))

    def _returns_fn(self, apply):
        from hds.algo.rollout import policy_rollout

        env, task = self.env, self.env.task

        def returns(params):
            def one(q, qd):
                state = env.sim.init(q, qd, env.params)
                _, _, r = policy_rollout(
                    env,
                    env.params,
                    task,
                    lambda o: apply(params, o),
                    state,
                    jax.random.PRNGKey(0),
                    0.0,
                    task.horizon,
                    self.low,
                    self.high,
                )
                return r.sum()

            return jax.vmap(one)(self.q0, self.qd0)

        return returns

    def zero_action(self) -> np.ndarray:
        """Returns [episodes] of doing nothing (u = 0 throughout)."""
        from hds.algo.rollout import open_loop_return

        env, task = self.env, self.env.task
        zeros = jnp.zeros((task.horizon, env.sim.n_act))

        @jax.jit
        def returns():
            def one(q, qd):
                return open_loop_return(
                    env, env.params, task, env.sim.init(q, qd, env.params), zeros
                )

            return jax.vmap(one)(self.q0, self.qd0)

        return np.asarray(returns())


def summary(values) -> dict:
    values = np.asarray(values, dtype=float)
    return {
        "mean": float(np.mean(values)),
        "min": float(np.min(values)),
        "max": float(np.max(values)),
        "n": int(values.size),
    }
