"""Where the trainer's programs' StableHLO ops come from: the reference configuration's chunk
(and init) lowered as `python -m hds.run` lowers them, every op attributed to the part of the
epoch it was traced in (issue 43).

An op's location names the Python frames it was traced under; an op inside a private function
(a scan body, a threefry, a `jnp.where`) is attributed through the call graph to the part whose
call site first calls that function. Counts are of `stablehlo.*` and `chlo.*` ops (those of
`bench.worker.hlo_size` plus the ones its line-based count misses, a few percent).

    PYTHONPATH=$PWD python experiments/test_suite_time/hlo_parts.py [analytic|tree] [--profile]

`--profile` also prints where tracing the chunk spends its time (cProfile, cumulative seconds:
inflated by the profiler, read them as shares).
"""

from __future__ import annotations

import collections
import re
import sys

import jax

import bench.common  # noqa: F401  (hds, which quiets XLA's log, before the backend starts)
from bench.common import REFERENCE, compose
from hds.algo.pods import make_train_from_config
from hds.envs import make_env

FRAME = re.compile(r'"([^"(]+)"\("([^"]+)":(\d+)')
RNG = ("threefry", "_threefry_split", "_uniform", "_normal", "_normal_real")


def functions(lowered):
    """Each function of the module: its ops (name, location); and each callee's call sites."""
    module = lowered.compiler_ir("stablehlo")
    ops: dict[str, list] = {}
    calls = collections.defaultdict(list)

    def walk(op, fname):
        for region in op.regions:
            for block in region.blocks:
                for o in block.operations:
                    name = o.operation.name
                    if name == "func.call":
                        callee = str(o.operation.attributes["callee"]).lstrip("@")
                        calls[callee].append((fname, str(o.location)))
                    ops[fname].append((name, str(o.location)))
                    walk(o.operation, fname)

    for f in module.body.operations:
        fname = str(f.operation.attributes["sym_name"]).strip('"')
        ops[fname] = []
        walk(f.operation, fname)
    return ops, dict(calls)


def part(loc: str) -> str | None:
    """The epoch's part an op's location names, or None (then its function's caller decides)."""
    frames = [(f, p.split("/")[-1], int(line)) for f, p, line in FRAME.findall(loc)]
    chain = " ".join(f"{p}:{f}" for f, p, _ in frames)
    if not frames:
        return None
    if "regress.py" in chain:
        if "shuffle.py" in chain:
            return "regress: shuffle (permutation)"
        if "minibatch_step" in chain:
            return "regress: minibatch step (grad, Adam)"
        if "train_epoch" in chain:
            return "regress: inner epoch (gather, loss)"
        return "regress: start loss, finite rows, early-stop cond"
    if "improve.py:improve" in chain:
        source = open(sys.modules["hds.algo.improve"].__file__).read().splitlines()
        line = [n for f, p, n in frames if p == "improve.py"][-1]
        text = source[line - 1]
        if "value_and_grad" in text:
            return "improve: value_and_grad of the return (rollout, its linearization, transpose)"
        if "jax.vmap(ret)" in text:
            return "improve: line search, the candidates' returns (one vmapped rollout)"
        return "improve: clip, candidates, accept"
    if "_Stages.collect" in chain:
        if "rollout.py" in chain:
            return "collect: policy rollout (policy, env step, reward)"
        return "collect: reset, keys"
    if "_Stages.improve" in chain:
        return "improve: keys, annealing"
    if "continuation.py" in chain:
        return "continuation"
    if "_metrics" in chain:
        return "metrics"
    if "regression_rows" in chain or "Split.used" in chain:
        return "split: regression rows"
    if "pods.py:make_train.<locals>.epoch" in chain:
        return "epoch: keys, glue"
    if "pods.py:make_train.<locals>.init" in chain:
        return "init: the policy's, Adam's and the continuation's"
    return None


def is_random(fname: str, calls, seen=()) -> bool:
    """A function of jax.random (threefry, its splits, uniform and normal draws), or one only
    they call (threefry's rounds)."""
    if fname.rstrip("0123456789_") in RNG or fname.startswith("threefry"):
        return True
    callers = [c for c, _ in calls.get(fname, []) if c not in seen]
    return bool(callers) and all(is_random(c, calls, (*seen, fname)) for c in callers)


def attribute(ops, calls) -> tuple[collections.Counter, collections.Counter]:
    """Ops per part, and of them those inside jax.random's functions. A random function's ops
    go to its caller's part whatever their own location says (jax reuses the trace of a
    threefry of one shape, with the frames of the first program that traced it)."""
    memo: dict[str, str] = {}

    def of_function(fname, seen=()):
        if fname == "main":
            return "chunk's scan, constants"
        if fname not in memo:
            parts = [
                part(loc) or of_function(caller, (*seen, fname))
                for caller, loc in calls.get(fname, [])
                if caller not in seen
            ]
            memo[fname] = parts[0] if parts else "?"
        return memo[fname]

    counts, random = collections.Counter(), collections.Counter()
    for fname, entries in ops.items():
        rng = is_random(fname, calls)
        for name, loc in entries:
            if name.startswith(("stablehlo.", "chlo.")):
                where = of_function(fname) if rng else part(loc) or of_function(fname)
                counts[where] += 1
                random[where] += rng
    return counts, random


def table(title: str, lowered, parts: bool = True) -> None:
    ops, calls = functions(lowered)
    counts, random = attribute(ops, calls)
    total = sum(counts.values())
    print(f"\n{title}: {total:,} ops in {len(ops)} functions\n")
    if not parts:  # one part; its jax.random functions may carry another program's frames
        print(f"{sum(random.values()):,} of them inside jax.random's functions")
        return
    print("| part | ops | share | of them jax.random's |\n| --- | --- | --- | --- |")
    for name, n in counts.most_common():
        print(f"| {name} | {n:,} | {n / total:.0%} | {random[name]:,} |")
    print(f"| all | {total:,} | 100% | {sum(random.values()):,} |")


def main() -> None:
    backend = next((a for a in sys.argv[1:] if not a.startswith("--")), "analytic")
    cfg = compose(*REFERENCE, f"env.backend={backend}")
    trainer = make_train_from_config(cfg, make_env(cfg.env))
    hparams, key = trainer.default_hparams, jax.random.PRNGKey(0)
    state = jax.eval_shape(trainer.init, key, hparams)
    if "--profile" in sys.argv:
        import cProfile
        import pstats

        profile = cProfile.Profile()
        profile.runcall(lambda: jax.jit(trainer.run_chunk).trace(state, hparams))
        pstats.Stats(profile).sort_stats("cumulative").print_stats(r"hds/|loops.py", 40)
    table("run_chunk", jax.jit(trainer.run_chunk).lower(state, hparams))
    table("init", jax.jit(trainer.init).lower(key, hparams), parts=False)


if __name__ == "__main__":
    main()
