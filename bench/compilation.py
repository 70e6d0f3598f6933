"""Section `compile`: cold and warm compile of the trainer, each in its own process; and
every program a method of the reference study compiles, with its trace, lowering and compile
seconds (bench.worker's `programs`).

Cold: a fresh, empty persistent compilation cache directory. Warm: a second process on the same
directory (the persistent cache, `hds.utils.runtime.enable_compilation_cache`, as `python -m
hds.run` enables it). The program is what hds.run compiles: jax.jit of trainer.init and of
trainer.run_chunk mapped over one seed (hds.utils.runtime.over_runs), on the reference
configuration.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

from bench.common import REFERENCE, load_average, run_worker
from hds.utils.runtime import program_cache_beside

# issue 43's targets for the reference configuration on 2 cores: a process from an empty
# compilation cache, and a second process of the same configuration
COLD_TARGET_S, WARM_TARGET_S = 8.0, 3.0

DEFAULT_BUDGET = {
    "backends": ["analytic", "generalized"],
    "overrides": [],  # config overrides on top of the reference configuration
    # per program: `python -m hds.run +experiment=sim2real_friction method=M`, each method in
    # its own process on an empty cache (pods_cl: the trainer and the evaluation; hds: the
    # dynamics model's training; pods_corrected: discovery's fit and the retraining)
    "methods": ["pods_cl", "hds", "pods_corrected"],
    "method_overrides": [],  # e.g. smaller budgets: algo.epochs=10
    # cold + warm pairs per backend, each on fresh caches: a row is the median's (a shared
    # host's idle process times vary by a third between runs: 7.4-11.1 s, 2026-11-28)
    "repeats": 5,
}
TOP = 8  # programs listed per method (the rest summed in one row)
# Python's bytecode cache on, as a user's second process has it (pip writes it on install, an
# editable install on first import): the shells these benchmarks ran from set
# PYTHONDONTWRITEBYTECODE, and each warm process compiled hds's ~55 modules from source
# again, ~0.2 CPU s of its ~2-3.5 (2026-11-28)
BYTECODE = {"PYTHONDONTWRITEBYTECODE": ""}


def entries_of(path: Path) -> set[str]:
    return {p.name for p in path.iterdir()}


def cache_size_mib(path: Path) -> float:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 2**20


def stamp() -> dict:
    """When and under what load an entry was measured: a partial rerun keeps the entries of
    earlier runs (`merge`), so each carries its own."""
    return {
        "measured_at": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "load": load_average(),
    }


def measure(backend: str, overrides: list[str]) -> dict:
    start = stamp()
    cache = Path(tempfile.mkdtemp(prefix="hds-bench-cache-"))
    try:
        spec = {
            "overrides": [*REFERENCE, f"env.backend={backend}", *overrides],
            "program": "chunk",
            "run": True,
            "cache": str(cache),
        }
        cold = run_worker("train", spec, env=BYTECODE)
        size, entries = cache_size_mib(cache), entries_of(cache)
        warm = run_worker("train", spec, env=BYTECODE)
        new = sorted(entries_of(cache) - entries)
    finally:
        shutil.rmtree(cache, ignore_errors=True)
        shutil.rmtree(program_cache_beside(cache), ignore_errors=True)
    # A warm process that writes a new run_chunk entry missed the cache: its program differed
    # from the cold one's (e.g. a source file edited in between, which changes the HLO's
    # source locations).
    return {
        "backend": backend,
        "overrides": overrides,
        **start,
        "load_after": load_average(),
        "cold": cold,
        "warm": warm,
        "cache_mib": size,
        "warm_hit": not any("run_chunk" in n for n in new),
        "warm_new_entries": new,
    }


def repeated(backend: str, overrides: list[str], repeats: int) -> dict:
    """`measure` `repeats` times: the cold row is the run of the median cold process, the warm
    row the run of the median warm one; every run's process seconds are kept (`spread`)."""
    runs = [measure(backend, overrides) for _ in range(max(repeats, 1))]

    def median_run(kind):
        ranked = sorted(runs, key=lambda r: r[kind]["process_s"])
        return ranked[(len(ranked) - 1) // 2]

    cold, warm = median_run("cold"), median_run("warm")
    spread = {k: [r[k]["process_s"] for r in runs] for k in ("cold", "warm")}
    return {
        **cold,
        "warm": warm["warm"],
        "warm_hit": all(r["warm_hit"] for r in runs),
        "warm_new_entries": sorted({n for r in runs for n in r["warm_new_entries"]}),
        "load_after": runs[-1]["load_after"],
        "spread": spread,
    }


def programs(method: str, overrides: list[str]) -> dict:
    start = stamp()
    cache = Path(tempfile.mkdtemp(prefix="hds-bench-cache-"))
    try:
        spec = {
            "overrides": [
                "+experiment=sim2real_friction",
                f"method={method}",
                "logger=none",
                *overrides,
            ],
            "cache": str(cache),
        }
        # the program cache off: each program keeps its own name in jax's log (with it, the
        # trainer's and the evaluation's are jax.export's `flat` and `call`)
        result = run_worker("programs", spec, env={"HDS_PROGRAM_CACHE": "off"})
        return {
            "method": method,
            "overrides": overrides,
            **start,
            "load_after": load_average(),
            **result,
        }
    finally:
        shutil.rmtree(cache, ignore_errors=True)


def program_rows(result: dict, top: int) -> list[list]:
    """The method's `top` programs by trace + lowering + compile seconds, then the rest in one
    row, then the whole."""

    def total(p):
        return p.get("trace_s", 0.0) + p.get("lower_s", 0.0) + p.get("compile_s", 0.0)

    ranked = sorted(result["programs"].items(), key=lambda item: -total(item[1]))
    size = result["chunk_size"]

    def row(name, entries):
        s = {k: sum(p.get(k, 0.0) for p in entries) for k in ("trace_s", "lower_s", "compile_s")}
        ops = (
            [size["stablehlo_ops"], size["hlo_instructions"]] if name == "run_chunk" else [None] * 2
        )
        return [
            result["method"],
            name,
            sum(p["count"] for p in entries),
            s["trace_s"],
            s["lower_s"],
            s["compile_s"],
            sum(s.values()),
            *ops,
        ]

    rows = [row(name, [p]) for name, p in ranked[:top]]
    rest = ranked[top:]
    if rest:
        rows.append(row(f"{len(rest)} other programs", [p for _, p in rest]))
    rows.append(row("all", [p for _, p in ranked]))
    rows[-1].append(result["run_s"])
    for r in rows[:-1]:
        r.append(None)
    return rows


def when(entry: dict) -> str:
    """The run an entry comes from: its time and the 1-minute load average before and after."""
    if "measured_at" not in entry:
        return "-"
    return f"{entry['measured_at']} (load {entry['load'][0]:g}/{entry['load_after'][0]:g})"


def run(budget: dict) -> dict:
    repeats = int(budget.get("repeats", 1))
    results = [repeated(b, budget["overrides"], repeats) for b in budget["backends"]]
    per_program = [programs(m, budget["method_overrides"]) for m in budget["methods"]]
    return section(results, per_program)


def merge(old: dict, new: dict) -> dict:
    """A rerun of some backends or methods (`--set compile.backends=tree`) replaces their rows
    and keeps the other rows of the stored section `old`; every row says which run it comes
    from. A row of an old section without its own stamp takes its section's."""
    if old.get("error") or new.get("error") or old.get("skipped"):
        return new

    def stamped(entries, section_):
        load = section_.get("load_before") or [float("nan")]
        default = {
            "measured_at": str(section_.get("measured_at", "?")),
            "load": load,
            "load_after": section_.get("load_after") or load,
        }
        return [{**default, **e} for e in entries]

    def union(key, field):
        fresh = {e[key] for e in new.get(field, [])}
        kept = [e for e in stamped(old.get(field, []), old) if e[key] not in fresh]
        return kept + list(new.get(field, []))

    return {**new, **section(union("backend", "data"), union("method", "programs"))}


def targets(results: list[dict]) -> list[dict]:
    """Issue 43's targets per backend: the reference configuration's process from an empty
    compilation cache, and a second process of it."""
    out = []
    for r in results:
        for kind, limit, what in (
            ("cold", COLD_TARGET_S, "a process from an empty compilation cache"),
            ("warm", WARM_TARGET_S, "a second process of the same configuration"),
        ):
            seconds = r[kind]["process_s"]
            runs = r.get("spread", {}).get(kind, [seconds])
            of = (
                f", median of {len(runs)}: {min(runs):.1f}-{max(runs):.1f}" if len(runs) > 1 else ""
            )
            out.append(
                {
                    "target": f"{r['backend']}: {what} <= {limit:g} s (reference configuration)",
                    "value": f"{seconds:.1f} s ({when(r)}{of})",
                    "met": bool(seconds <= limit),
                }
            )
    return out


def section(results: list[dict], per_program: list[dict]) -> dict:
    """The section's tables, targets and notes from its entries (those of one run, or of
    several merged: each row names its run)."""
    rows = []
    for r in results:
        for kind in ("cold", "warm"):
            m = r[kind]
            hit = "yes" if kind == "cold" or r["warm_hit"] else "no (missed)"
            rows.append(
                [
                    r["backend"],
                    kind,
                    hit if kind == "warm" else "-",
                    m["import_s"],
                    m["build_s"],
                    m["init_s"],
                    m["trace_s"],
                    m["compile_s"],
                    m["run_s"],
                    m["process_s"],
                    m.get("process_cpu_s"),
                    when(r),
                ]
            )
    overrides = sorted({o for r in results for o in r.get("overrides", [])})
    method_overrides = sorted({o for r in per_program for o in r.get("overrides", [])})
    program_table = []
    for res in per_program:
        for r in program_rows(res, TOP):
            program_table.append([*r, when(res)])
    tables = [
        {
            "caption": "Seconds, each row its own process (reference configuration"
            + "".join(f", {o}" for o in overrides)
            + ", 1 seed; init (jit): init traced, its XLA compile and run on a second thread "
            "while the chunk is traced and compiled (hds.utils.runtime.start_and_compile; "
            "before 2026-11-28 10:30 UTC, all three); XLA compile: the chunk's, and the wait "
            "for init; run = one compiled chunk of epochs; process CPU s: user + system "
            "seconds of the process, less inflated than its wall time on a loaded machine; "
            "measured: the run the row comes from, UTC, with the 1-minute load average "
            "before/after it; where a backend was measured several times (budget `repeats`, "
            "each a cold and a warm process on fresh caches), its cold row is the run of the "
            "median cold process and its warm row that of the median warm one, and the "
            "targets below give the runs' range)",
            "columns": [
                "backend",
                "cache",
                "cache hit",
                "imports",
                "env build",
                "init (jit)",
                "trace",
                "XLA compile",
                "run chunk",
                "process total",
                "process CPU s",
                "measured (load)",
            ],
            "rows": rows,
        },
        {
            "caption": "Seconds per program, each method its own process from an empty "
            "cache and the program cache off: python -m hds.run +experiment=sim2real_friction "
            "method=M"
            + "".join(f" {o}" for o in method_overrides)
            + " (5 seeds; every program jax traced, lowered and compiled, from its own "
            "log records; ops: the trainer chunk's StableHLO ops as lowered and HLO "
            "instructions after XLA's optimisation)",
            "columns": [
                "method",
                "program",
                "compiles",
                "trace",
                "lower",
                "XLA compile",
                "total",
                "StableHLO ops",
                "HLO instructions",
                "whole run",
                "measured (load)",
            ],
            "rows": program_table,
        },
    ]
    return {
        "title": "cold and warm (persistent cache) compile",
        "tables": [t for t in tables if t["rows"]],
        "targets": targets(results),
        "notes": [
            "Cache sizes after the cold run: "
            + ", ".join(f"{r['backend']} {r['cache_mib']:.1f} MiB" for r in results)
            + ".",
            "A warm process reads the trainer's init and chunk from the program cache (trace: "
            "deserializing and lowering it, hds.utils.runtime.program_key) and their XLA "
            "compile from the persistent compilation cache; it builds no brax System and never "
            "imports brax, mujoco.mjx, matplotlib or Orbax (hds.envs.system.LazySystem: the "
            "engine's check of the model is kept in the program cache too) and reads the "
            "composed config from the program cache (hds.config.compose); it still imports "
            "jax, optax, mujoco and Hydra, loads the chunk's executable (XLA's "
            "deserialization, proportional to the program's code) and runs init and the "
            "chunk. A warm miss means the warm process's program differed from the cold one's "
            "(source files edited in between change the HLO's source locations).",
            "A rerun of some backends or methods (`--set compile.backends=tree`) replaces "
            "their rows and keeps the others; compare rows measured under similar load.",
            "Where a warm process's seconds go (2026-11-28, 2-core AMD EPYC shared, load ~5; "
            "python -X importtime, cProfile, JAX_LOG_COMPILES=1 of bench.worker train): "
            "analytic and tree import the same modules and compile the same programs; they "
            "differ in the chunk's XLA executable only (analytic 4686 StableHLO lines, 468 KiB "
            "compressed, against 4413 and 422 KiB): its load (XLA's native "
            "deserialize_executable, ~97% of the 'XLA compile' column; the cache key ~30 ms) "
            "took 0.43-0.50 CPU s against 0.31-0.42, and deserializing + lowering the exported "
            "program 0.18-0.25 against 0.13-0.21. Imports after jax: Hydra ~0.1 CPU s (hds.config "
            "registers its schemas with Hydra's ConfigStore on import, and validation parses "
            "overrides with Hydra: kept, as Hydra compositions expect the store filled), "
            "mujoco ~0.2 (half of it glfw, found by mujoco's renderer import), flax.linen ~0.2 "
            "(absl.flags alone ~0.08), optax ~0.15 (optax.contrib), hds's own modules "
            "~0.2 (the schemas' dataclasses, hds.config's ConfigStore registration).",
            "Eager programs of a warm process: 10 before (4 in the trainer's build, one in the "
            "program cache's key, iota/threefry/broadcast for the seeds and hyperparameters), 6 "
            "now: the build's model counts and the key's dtypes are read in numpy "
            "(hds.algo.pods._model_count, hds.utils.runtime.cached_lowering). Measured A/B on "
            "the same load (4 alternating warm processes each): 3.30 CPU s before, 3.36 after: "
            "the cut (~0.05 s) is within the load's noise.",
            "A cold process, 2026-11-28 (2-core AMD EPYC shared with four sessions; cold "
            "bench.worker train processes of the reference configuration, before/after "
            "alternating, each on fresh caches; CPU s, as the wall time at load 4-13 is 2-15x "
            "the idle one): the analytic and tree backends' System is built from MuJoCo's "
            "model without brax (hds.envs.mjsystem: no import of brax, mujoco.mjx, "
            "scipy.spatial or trimesh, none of load_model's 36 small compiles; the same "
            "leaves and the same lowered programs), and init compiles and runs on a second "
            "thread while the chunk is traced and compiled "
            "(hds.utils.runtime.start_and_compile). Tree, System only (09:51, load 4.3/4.0 "
            "and 3.7/3.6): env build 1.24 -> 0.21 and 1.40 -> 0.33 s, process 13.7 -> 11.4 "
            "and 16.3 -> 14.8 CPU s (12.2 -> 8.4 and 16.1 -> 14.8 s wall). Both changes "
            "(10:03-10:19, load 6-13): tree 18.8 -> 17.0, 17.0 -> 15.9, 17.9 -> 16.2 CPU s; "
            "10:22-10:24, load 4-7: tree 13.8 -> 12.3 and 15.3 -> 15.1 CPU s (22.3 -> 19.1 and "
            "36.5 -> 42.0 s wall); analytic 21.5 -> 17.7, 19.4 -> 20.7, 20.5 -> 17.0 CPU s; "
            "env build 2.4-18.5 s -> 0.5-1.8 s wall at those loads; init's own column (its "
            "trace, now) 0.28-1.2 s against 2.1-8.5. Idle, the build's ~1 s and init's "
            "compile and run (~0.5 s) should leave the cold tree process at ~8 s: the rows "
            "above are the measure. A warm process is not slower (10:31-10:33, load 8-11, tree: "
            "2.67 -> 2.31 and 2.13 -> 2.10 CPU s; their cold ones 17.4 -> 14.1, 14.1 -> 12.7).",
            "Cut since (2026-11-28, 2-core AMD EPYC shared): a warm process no longer imports "
            "flax (hds's states are hds.utils.pytree dataclasses, the policy's flax module is "
            "made on first use: hds.networks.Policy) nor GLFW (hds.run, hds.loop, hds.discover "
            "and bench.worker import MuJoCo with MUJOCO_GL=disable, "
            "hds.utils.runtime.headless_mujoco; they render in child processes only). optax "
            "stays: init's output structure, read from the program cache, holds its state "
            "types. And the workers run with Python's bytecode cache (BYTECODE): the shells "
            "these runs came from set PYTHONDONTWRITEBYTECODE, so each warm process compiled "
            "hds's ~55 modules from source again, where a user's second process reads them. "
            "Warm analytic processes, alternating, CPU s mean (median): idle (load 0.7-0.9, 5 "
            "each) 1.96 (1.97) before, 1.89 (1.84) after the two cuts, 1.88 (1.76) with the "
            "bytecode cache too; at load 10-11 (9 each) 2.42, 2.29, 2.18. Trained numbers "
            "unchanged (the state after init + a chunk, every leaf, analytic and tree, from jit "
            "and from the program cache; python -m hds.run +experiment=sim2real_friction "
            "method=pods_cl seeds=2 algo.epochs=4: summary.json and the saved policies byte for "
            "byte). The rows above (10:40 UTC) are idle; this host (kernel "
            "6.18.44-fc-v669) runs the warm process in ~1.8 CPU s where the 07:07 UTC rows' "
            "(v657, load ~5) took 3.3-3.5.",
            "Tried and dropped: keeping the compiled XLA executable itself in the program "
            "cache (jax.experimental.serialize_executable) instead of the exported program and "
            "jax's persistent cache: its load took 0.70-0.91 CPU s against 0.52-0.61 for "
            "deserialize + lower + persistent-cache load, and an executable that was itself "
            "loaded from the persistent cache serializes broken ('Function ... not found' when "
            "run). XLA's xla_cpu_parallel_codegen_split_count=1: load 0.51-0.56 against "
            "0.39-0.41 CPU s. The same flag at 2 and 8 on the cold process (tree, 3 pairs "
            "each, idle, 2026-11-28 11:32 UTC): 11.2 and 11.0 s against 8.5 s for XLA's "
            "default.",
            "init compiled at hds.utils.runtime.RUN_ONCE (LLVM -O1, XLA's classic CPU "
            "emitters; 2026-11-28, this host, idle): its XLA compile 0.40-0.43 against "
            "0.92-1.01 CPU s (3 each), outputs the same to the last bit; cold tree processes, "
            "6 interleaved pairs on fresh caches: the chunk's trace (beside init's compile) "
            "0.16-0.80 s shorter in every pair, the process 0.47 s shorter on average (5 of "
            "6). Options that keep the chunk's numbers, each its own process compiling the "
            "reference chunk (tree, 4 alternating rounds, idle, 12:05 UTC): "
            "xla_cpu_emitter_verification_level=0, "
            "xla_cpu_enable_concurrency_optimized_scheduler=false and "
            "xla_llvm_disable_expensive_passes=true compiled in 3.65-4.42, 3.83-4.79 and "
            "3.92-5.08 s against 3.98-4.66 s for XLA's default: none pays. Neither did tracing "
            "the open-loop rollout once for its gradient and its line search (a jitted "
            "function called twice: 1.69-1.91 s against 1.68-1.72 s for export's trace).",
            "The analytic engine's step rematerialised (jax.checkpoint, as the tree engine's; "
            "2026-11-28 18:32 UTC, load ~1.4, cold bench.worker train processes of the "
            "reference configuration, 3 interleaved pairs on fresh caches): the chunk's XLA "
            "compile 4.04-4.29 s against 4.96-5.06 s, the process 8.13-8.41 s against "
            "8.78-9.52 s; a compiled chunk of 5 epochs ran in 0.092-0.119 s against "
            "0.093-0.123 s (5 alternating processes each, median of 7 calls). The trained "
            "numbers move in float32's last digits, which training amplifies: make run's "
            "mean real returns -4.12, -4.63, -3.35, -3.31 (pods_cl, hds, corrected, oracle) "
            "against -3.95, -4.76, -3.30, -3.28, each inside the other's 95% interval.",
            "The same trainer code, three runs of this section on this host, idle before each "
            "(2026-11-28, the median of 5 cold processes, their range): 19:46 UTC analytic "
            "8.1 s (7.6-9.3), tree 8.8 s (8.5-10.3); 19:57 analytic 7.3 s (7.0-7.9), tree "
            "7.1 s (6.9-7.3); 20:28 (the rows above) analytic 9.0 s (8.6-10.1), tree 8.2 s "
            "(7.7-8.9). The host's speed drifts by a quarter within the hour, so the 8 s "
            "target is met on some runs and missed on others: over the 15 cold analytic "
            "processes it is not met reliably.",
            "Where the chunk's XLA compile goes (2026-11-28 23:08 UTC, this host, idle; `perf "
            "record -F 999 -g` of a process that lowers the reference chunk, analytic, and "
            "compiles it; CPU s from the samples' call chains): 4.2 s wall, ~5.9 CPU s on the "
            "two cores. LLVM compiling the kernels to machine code 3.4 (its optimisation "
            "passes 1.6, instruction selection and emission 1.7), XLA's fusion emitters "
            "(MLIR to LLVM IR, a kernel at a time) 1.3, the main thread's HLO passes 0.43 and "
            "thunk emission 0.40, MLIR's dialect loading 0.47. The optimised program has 437 "
            "fusion kernels and 377 copies: the cost is per kernel (~8 ms of LLVM each), so "
            "only fewer kernels would cut it much. Tried on the same chunk, alternating "
            "processes: jax_default_prng_impl=rbg and unsafe_rbg (one RNG op in place of "
            "threefry's unrolled rounds; 8,034 and 8,682 HLO instructions against 7,446) "
            "compiled in 4.22-4.52 and 3.67-3.68 s against 3.72-3.87 s (2 rounds), so the "
            "random bits are not where the time goes (and they would change every trained "
            "number); LLVM -O1 (xla_backend_optimization_level=1) in 3.56-3.95 s against "
            "4.09-4.63 s (3 rounds), its 5-epoch chunk as fast (0.085-0.110 s against "
            "0.099-0.104 s) but its numbers not the same to the last bit, -O0 in 2.50-2.65 s "
            "with the chunk 4 times slower (0.41-0.44 s); xla_cpu_prefer_vector_width=128 "
            "3.90 s against 4.00 s, numbers not the same. None is taken: -O1's ~0.5 s would "
            "leave the cold process at the target's edge, with every trained number moved.",
        ],
        "data": results,
        "programs": per_program,
    }
