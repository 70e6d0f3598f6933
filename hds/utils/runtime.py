"""Process-wide JAX set-up: the persistent compilation cache (a second process skips compiling)."""

from __future__ import annotations

import concurrent.futures
import functools
import hashlib
import logging
import os
import sys
import time
from pathlib import Path

import jax
import numpy as np

DEFAULT_CACHE = Path(os.environ.get("HDS_JAX_CACHE", Path.home() / ".cache" / "hds" / "jax"))


def enable_compilation_cache(path: str | Path | None = None) -> Path:
    """Turn on JAX's persistent compilation cache at `path` (default: $HDS_JAX_CACHE or
    ~/.cache/hds/jax). Without a path, a cache this process already set up is kept as it is
    (its settings included)."""
    configured = jax.config.jax_compilation_cache_dir
    if path is None and configured:
        return Path(configured)
    path = Path(path or DEFAULT_CACHE).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    # every program, however small: a run compiles ~150 small ones (eager ops, helpers) of
    # 0.01-0.5 s, ~9 s in all, which a cached read makes ~10 s less CPU for each later process
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def command_gc() -> None:
    """Garbage collection for a command-line process, called once its modules are imported:
    the objects made so far (jax's, flax's, Hydra's modules, their classes and tables: they
    live as long as the process) leave every later collection (gc.freeze), which walked them
    all again in each full collection; and the interpreter's last collections at exit are
    skipped (they walked every object again, ~0.6 s of a second process's ~4 s idle, to free
    memory the OS frees anyway). Objects are still freed by their reference counts; only
    unreachable cycles are left to the OS, as Python never promises their finalizers at exit.
    For command-line entry points, which write their outputs before they return."""
    import atexit
    import gc

    gc.freeze()
    atexit.register(gc.freeze)


def headless_mujoco() -> None:
    """Import MuJoCo with its in-process OpenGL off (MUJOCO_GL=disable while it is imported),
    where MUJOCO_GL is not set and MuJoCo is not imported yet; for command-line entry points,
    before they import hds's modules. A command renders only in child processes, which set
    MUJOCO_GL themselves (hds.render), while MuJoCo's default on Linux, GLFW, cost each process
    ~0.05 s at import (its library search starts a Python subprocess for a version check).
    MUJOCO_GL is left unset again afterwards, so children choose their own backend."""
    if "mujoco" in sys.modules or "MUJOCO_GL" in os.environ:
        return
    os.environ["MUJOCO_GL"] = "disable"
    try:
        import mujoco  # noqa: F401
    finally:
        del os.environ["MUJOCO_GL"]


def pyplot():
    """matplotlib's pyplot, headless (Agg), imported on the first figure: a process that draws
    none (a training whose programs come from the program cache) skips its ~0.4 s import."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def cpu_workers(threads: int = 0) -> int:
    """How many independent programs a process runs at once on threads (a batch's runs,
    discovery's fits): `threads`, or (0) one per core this process may use where jax runs on
    the CPU, whose XLA runs a program's loops on one core (two runs of the reference
    configuration in 0.40 s against 0.78 s one after the other, 2 cores); one on an
    accelerator, which runs one program at a time. Each program's numbers are the same
    whichever thread runs it."""
    if threads > 0:
        return int(threads)
    if jax.default_backend() != "cpu":
        return 1
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def runs_vmapped(setting: int | None, runs: int) -> int:
    """How many runs of a batch one program vmaps at a time. `None` (auto): all of them where the
    batch is sharded across several devices or runs on an accelerator; one on a single CPU,
    where a vmapped epoch costs more than its runs one after another (a batched `lax.cond`
    runs both branches, batched matmuls and gathers are slower) and where a run's numbers
    should not depend on how many ran beside it. 0: all of them."""
    if setting is None:
        one_cpu = jax.default_backend() == "cpu" and jax.device_count() == 1
        return 1 if one_cpu else runs
    return runs if setting == 0 else min(setting, runs)


def over_runs(fn, vmapped: int, runs: int):
    """`fn` mapped over the leading axis of its arguments (a batch of `runs` runs), `vmapped` at
    a time in one compiled program: a `jax.lax.map` loop over single runs (never a vmap of one),
    `jax.vmap` over all of them, or a loop over vmapped groups."""
    if vmapped == 1:  # lax.map's batch_size would vmap groups of one
        return lambda *args: jax.lax.map(lambda a: fn(*a), args)
    if vmapped >= runs:
        return jax.vmap(fn)
    return lambda *args: jax.lax.map(lambda a: fn(*a), args, batch_size=vmapped)


class RunByRun:
    """`fn` of one run, jitted once and called on each run of a batch (the leading axis of
    every argument) in a host loop, the results stacked: how a single CPU trains a batch
    (`runs_vmapped` 1). The program has one run's shapes, so every batch of runs of one
    configuration (1 seed or 5, a sweep of step sizes or friction gaps, a plant's draw) and
    every later process shares one compile and one persistent-cache entry, where a `lax.map`
    over the batch compiled a program per batch size. Each run's numbers are bit for bit those
    of the `lax.map` (the same loop body). On a CPU the runs are called on `threads` threads
    (`cpu_workers`: 0, one per core), each run's numbers the same whichever thread runs it.
    `lower(*args).compile()` mirrors `jax.jit`'s AOT API; with a `key` (`program_key`), it
    reads the lowered program from the program cache, or writes it there."""

    def __init__(self, fn, compiled=None, key: str | None = None, threads: int = 0):
        self.fn, self.key, self.threads = fn, key, threads
        self.program = compiled  # None: compiled (from the program cache) on the first call

    def __call__(self, *args):
        host = jax.tree.map(np.asarray, args)  # one run's slice is a view, not an eager op
        if self.program is None:  # called without lower(): compiled once, before any thread
            self.program = self.lower(*host).compile().program
        runs = jax.tree.leaves(host)[0].shape[0]

        def run(i):  # waits for its run: calls dispatched from one thread run one at a time
            return jax.block_until_ready(self.program(*jax.tree.map(lambda x: x[i], host)))

        workers = min(cpu_workers(self.threads), runs)
        if workers > 1:  # XLA runs a run's loops on one core: the runs share the cores
            pool = concurrent.futures.ThreadPoolExecutor(workers, thread_name_prefix="hds-run")
            with pool:
                outs = list(pool.map(run, range(runs)))
        else:
            outs = [run(i) for i in range(runs)]
        return jax.tree.map(lambda *xs: jax.device_put(np.stack(xs)), *outs)

    def lower(self, *args):
        """One run's program for the batch `args` (arrays, or jax.ShapeDtypeStruct: the
        program needs their shapes and dtypes only)."""
        first = jax.tree.map(_first_run, args)
        return _LoweredRuns(self.fn, lowered_program(self.fn, first, self.key), self.threads)


def _first_run(x):
    if isinstance(x, jax.ShapeDtypeStruct):
        return jax.ShapeDtypeStruct(x.shape[1:], x.dtype)
    return np.asarray(x)[0]


class _LoweredRuns:
    def __init__(self, fn, lowered, threads: int = 0):
        self.fn, self.lowered, self.threads = fn, lowered, threads

    def compile(self, compiler_options: dict | None = None) -> RunByRun:
        return RunByRun(self.fn, self.lowered.compile(compiler_options), threads=self.threads)

    @property
    def out_info(self):
        """One run's outputs: their shapes and dtypes (jax.ShapeDtypeStruct)."""
        if isinstance(self.lowered, _CachedLowered):
            return jax.tree.unflatten(self.lowered.out_tree, self.lowered.lowered.out_info)
        return self.lowered.out_info


# XLA's options for a program a process runs once (the trainer's init): LLVM at -O1 and XLA's
# classic CPU emitters compile it in ~40% of the CPU time of XLA's defaults (0.40 against 0.95
# CPU s, the reference configuration's init), and its outputs are the same to the last bit
# (tests/test_program_cache.py). On one CPU that compile shares the cores with the chunk's
# trace (start_and_compile): 0.3 s less trace, ~0.4 s less for the cold process (bench/RESULTS.md,
# section "compile"). A program that runs for longer than it compiles keeps XLA's defaults:
# with the classic emitters the reference chunk ran ~1.6 times slower and its numbers moved in
# the 7th digit (experiments/test_suite_time/README.md).
RUN_ONCE = {"xla_backend_optimization_level": 1, "xla_cpu_use_fusion_emitters": False}


def start_and_compile(init: RunByRun, chunk: RunByRun, keys, hparams, prepare=None, timing=None):
    """`state = prepare(init(keys, hparams))` and `chunk.lower(state, hparams).compile()`: the
    same two programs as called one after the other, with init's XLA compile (at RUN_ONCE) and
    its run on a second thread while this one traces and compiles the chunk (from init's
    output shapes).
    XLA compiles a program on one core and releases the GIL meanwhile, so on two cores init's
    ~0.5-1 s leaves a cold process's wall time (bench/RESULTS.md, section "compile"). Returns
    (state, compiled chunk); `timing` (a dict) gets `init_s` (init traced), `trace_s` (the
    chunk traced) and `compile_s` (the chunk compiled, init compiled and run)."""
    import concurrent.futures

    timing = {} if timing is None else timing
    start = time.perf_counter()
    lowered = init.lower(keys, hparams)
    runs = jax.tree.leaves(keys)[0].shape[0]
    batch = jax.tree.map(
        lambda s: jax.ShapeDtypeStruct((runs, *s.shape), s.dtype), lowered.out_info
    )
    with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="hds-init") as pool:
        first_state = pool.submit(lambda: lowered.compile(RUN_ONCE)(keys, hparams))
        timing["init_s"] = (traced := time.perf_counter()) - start
        program = chunk.lower(batch, hparams)
        timing["trace_s"] = (compiling := time.perf_counter()) - traced
        compiled = program.compile()
        state = first_state.result()
    state = prepare(state) if prepare else state
    if _abstract(state) != _abstract(batch):  # a prepared state of other shapes: its own program
        compiled = chunk.lower(state, hparams).compile()
    timing["compile_s"] = time.perf_counter() - compiling
    return state, compiled


def _abstract(tree):
    leaves, structure = jax.tree.flatten(tree)
    return structure, [(tuple(x.shape), np.dtype(x.dtype)) for x in leaves]


# --- the program cache: the trainer's traced and lowered program, kept across processes -------
# jax's persistent cache keeps XLA's compile, not the Python work before it: a second process
# of a configuration traced and lowered the trainer's chunk again (3.2 s of its 9 s idle, the
# reference configuration). The cache below keeps that program, serialized by jax.export, under
# a key of everything the program is built from; where anything it closes over cannot be
# hashed, nothing is cached (a key that can miss nothing, or no cache).
log = logging.getLogger(__name__)
_OFF = ("0", "off", "none", "false", "no")


def program_cache_dir() -> Path | None:
    """Where traced programs are kept: $HDS_PROGRAM_CACHE (`off` turns the cache off), else
    beside jax's persistent compilation cache (<its directory>-programs); None where neither
    is set up (the cache is off)."""
    setting = os.environ.get("HDS_PROGRAM_CACHE", "")
    if setting.lower() in _OFF:
        return None
    if setting:
        return Path(setting).expanduser()
    configured = jax.config.jax_compilation_cache_dir
    return program_cache_beside(Path(configured)) if configured else None


def program_cache_beside(compilation_cache: Path) -> Path:
    """The program cache's default directory: beside the compilation cache, <its name>-programs."""
    return compilation_cache.with_name(compilation_cache.name + "-programs")


@functools.cache
def source_digest() -> str:
    """A hash of every file of the hds package (code, configs, models): any edit misses."""
    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        if path.is_file() and "__pycache__" not in path.parts:
            h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()


@functools.cache
def _versions() -> tuple[str, ...]:
    """The versioned libraries' versions (importlib.metadata reads are ~10 ms each: once)."""
    from importlib.metadata import PackageNotFoundError, version

    out = []
    for name in _VERSIONED:
        try:
            out.append(f"{name}={version(name)}")
        except PackageNotFoundError:
            out.append(f"{name}=none")
    return tuple(out)


def environment_digest() -> str:
    """The libraries' versions, the backend and jax's settings (those that are not cache or log
    settings): a program is reused only where all are the same."""
    parts = [jax.default_backend(), str(jax.devices()[0].device_kind), str(jax.device_count())]
    parts += [sys.version, *_versions()]
    settings = {k: v for k, v in jax.config.values.items() if "cache" not in k and "log" not in k}
    parts.append(repr(sorted(settings.items(), key=lambda kv: kv[0])))
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


# packages whose code the key covers by version (and hds by `source_digest`); a function or
# module from anywhere else (a user's effect, reward or helper) is hashed by its file and the
# globals it reads, which bytecode alone does not show
_VERSIONED = ("jax", "jaxlib", "brax", "mujoco", "flax", "optax", "numpy", "scipy")


def _covered(module_name: str | None) -> bool:
    top = (module_name or "").split(".")[0]
    return top in ("hds", *_VERSIONED) or top in sys.stdlib_module_names


def _file_bytes(module) -> bytes:
    path = getattr(module, "__file__", None)
    if not path or not Path(path).is_file():
        raise Unhashable(f"module {getattr(module, '__name__', module)!r} without a source file")
    return Path(path).read_bytes()


def _names_read(code) -> set[str]:
    names = set(code.co_names)
    for c in code.co_consts:
        if hasattr(c, "co_code"):
            names |= _names_read(c)
    return names


class Unhashable(Exception):
    """Something a program closes over that `fingerprint` cannot hash: nothing is cached."""


def fingerprint(obj, h=None, _path: tuple = ()) -> str:
    """A hash of `obj`'s content, followed through containers, dataclasses, arrays and the
    closures, defaults and bound objects of functions (code itself is covered by
    `source_digest` and the libraries' versions). Raises Unhashable on anything else."""
    import dataclasses
    import enum
    import types

    top = h is None
    h = h or hashlib.sha256()
    if any(obj is seen for seen in _path):  # a cycle: its position is its content
        h.update(b"cycle")
        return ""
    path = (*_path, obj)

    def put(tag: str, data: bytes = b""):
        h.update(tag.encode() + b"\0" + data + b"\1")

    if obj is None or isinstance(obj, bool | int | float | complex | str | bytes):
        put(type(obj).__name__, repr(obj).encode())
    elif isinstance(obj, enum.Enum):
        put("enum", f"{_name_of(type(obj))}.{obj.name}".encode())
    elif isinstance(obj, jax.core.Tracer):
        raise Unhashable("a traced value")
    elif isinstance(obj, np.ndarray | np.generic | jax.Array):
        a = np.asarray(obj)
        put("array", f"{a.dtype}{a.shape}".encode() + np.ascontiguousarray(a).tobytes())
    elif isinstance(obj, dict):
        put("dict", str(len(obj)).encode())
        for k in sorted(obj, key=repr):
            fingerprint(k, h, path)
            fingerprint(obj[k], h, path)
    elif isinstance(obj, list | tuple | set | frozenset):
        items = sorted(obj, key=repr) if isinstance(obj, set | frozenset) else obj
        put(_name_of(type(obj)), str(len(items)).encode())
        for x in items:
            fingerprint(x, h, path)
    elif isinstance(obj, type):
        put("type", _name_of(obj).encode())
        if not _covered(obj.__module__) and sys.modules.get(obj.__module__) is not None:
            fingerprint(sys.modules[obj.__module__], h, path)
    elif isinstance(obj, types.ModuleType):
        put("module", obj.__name__.encode())
        if not _covered(obj.__name__):
            put("file", _file_bytes(obj))
    elif isinstance(obj, functools.partial):
        put("partial")
        for part in (obj.func, obj.args, obj.keywords):
            fingerprint(part, h, path)
    elif isinstance(obj, types.MethodType):
        put("method", _name_of(obj.__func__).encode())
        fingerprint(obj.__self__, h, path)
    elif isinstance(obj, types.FunctionType):
        put("function", _name_of(obj).encode() + _code_bytes(obj.__code__))
        cells = [c.cell_contents for c in obj.__closure__ or ()]
        for part in (cells, obj.__defaults__, obj.__kwdefaults__):
            fingerprint(part, h, path)
        if not _covered(obj.__module__):  # its module's constants and helpers, as they are now
            module = sys.modules.get(obj.__module__)
            if module is not None and getattr(module, "__file__", None):
                put("file", _file_bytes(module))
            read = sorted(n for n in _names_read(obj.__code__) if n in obj.__globals__)
            for name in read:
                put("global", name.encode())
                fingerprint(obj.__globals__[name], h, path)
    elif isinstance(obj, types.BuiltinFunctionType | np.ufunc):
        put("builtin", _name_of(obj).encode() + repr(obj).encode())
    elif type(obj).__name__ == "MjModel" and type(obj).__module__.startswith("mujoco"):
        import mujoco

        buffer = np.empty(mujoco.mj_sizeModel(obj), np.uint8)
        mujoco.mj_saveModel(obj, None, buffer)
        put("mjmodel", buffer.tobytes())
    elif dataclasses.is_dataclass(obj):
        put("dataclass", _name_of(type(obj)).encode())
        for f in dataclasses.fields(obj):
            put("field", f.name.encode())
            fingerprint(getattr(obj, f.name), h, path)
    else:
        where = " > ".join(type(x).__name__ for x in path)
        raise Unhashable(f"{_name_of(type(obj))} (at {where})")
    return h.hexdigest() if top else ""


def _code_bytes(code) -> bytes:
    """A function's bytecode with its constants and the names it reads: a function outside hds
    (a user's effect) edited in place changes these, where `source_digest` does not see it."""
    consts = [_code_bytes(c) if hasattr(c, "co_code") else repr(c).encode() for c in code.co_consts]
    return code.co_code + b"\0".join([*consts, *(n.encode() for n in code.co_names)])


def _flat(fn, in_tree, out_trees: list):
    def flat(*leaves):
        out = fn(*jax.tree.unflatten(in_tree, leaves))
        leaves_out, tree = jax.tree.flatten(out)
        out_trees.append(tree)
        return leaves_out

    return flat


class _Unflatten:
    """A flat compiled program called with, and returning, the pytrees of the traced one."""

    def __init__(self, compiled, out_tree):
        self.compiled, self.out_tree = compiled, out_tree

    def __call__(self, *args):
        return jax.tree.unflatten(self.out_tree, self.compiled(*jax.tree.leaves(args)))


def program_key(*parts) -> str | None:
    """The program cache's key of a program built from `parts` (a config, the function it
    traces, with everything that function closes over): their content, every hds source file,
    the libraries' versions, the backend and jax's settings. None (no caching) where the cache
    is off or a part cannot be hashed."""
    if program_cache_dir() is None:
        return None
    try:
        return content_key(*parts)
    except Unhashable as err:
        log.info("program cache: not used, the program closes over %s", err)
        return None


def content_key(*parts) -> str:
    """The one key scheme of everything kept across processes: the content of `parts`
    (`fingerprint`), every hds source file, the libraries' versions, the backend and jax's
    settings. Raises Unhashable where a part cannot be hashed."""
    content = fingerprint(parts)
    return hashlib.sha256(f"{content}{source_digest()}{environment_digest()}".encode()).hexdigest()


def cached_build(kind: str, build, *parts):
    """`build()`'s result, kept pickled in the program cache's directory under `kind` and the
    `content_key` of `parts` (everything the result is built from, deterministically): a later
    process with the same key unpickles it instead of building. Where the cache is off, a part
    cannot be hashed, or the result cannot be pickled, it is built as before; an unreadable
    entry is built again and rewritten."""
    import pickle

    from hds.utils.io import atomic_write_bytes

    directory = program_cache_dir()
    if directory is None:
        return build()
    try:
        path = directory / f"{content_key(kind, *parts)}.{kind}.pickle"
    except Unhashable as err:
        log.info("program cache: %s not kept, it is built from %s", kind, err)
        return build()
    if path.is_file():
        try:
            return pickle.loads(path.read_bytes())
        except Exception as err:  # noqa: BLE001 - a damaged entry is built again
            log.warning("program cache: %s unreadable (%s); building again", path.name, err)
    value = build()
    try:
        blob = pickle.dumps(value)
    except Exception as err:  # noqa: BLE001 - nothing is kept; the result is the same
        log.info("program cache: %s not kept, it cannot be pickled (%s)", kind, err)
        return value
    try:
        atomic_write_bytes(path, blob)
    except OSError as err:  # a read-only cache: this process's result stands
        log.warning("program cache: %s not written (%s)", path.name, err)
    return value


def cached_lowering(fn, args: tuple, key: str, directory: Path):
    """`jax.jit(fn).lower(*args)`'s program kept in `directory` under `key` (plus the arguments'
    shapes and structure): a later process with the same key deserializes it instead of
    tracing `fn`. Returns an object whose `compile()` gives a callable of `fn`'s signature, or
    None where jax.export cannot carry the program (the reason is logged; call jit instead)."""
    import pickle

    from jax import export

    from hds.utils.io import atomic_write_bytes

    leaves, in_tree = jax.tree.flatten(args)
    # each leaf's dtype as jax will see it, without converting it (an eager op per dtype)
    dtypes = [x.dtype if hasattr(x, "dtype") else np.result_type(x) for x in leaves]
    avals = [
        (str(np.shape(x)), str(jax.dtypes.canonicalize_dtype(d)))
        for x, d in zip(leaves, dtypes, strict=True)
    ]
    digest = hashlib.sha256(f"{key}\n{in_tree}\n{avals}".encode()).hexdigest()
    path, tree_path = directory / f"{digest}.jaxexport", directory / f"{digest}.tree"
    exported = out_tree = None
    if path.is_file() and tree_path.is_file():
        try:
            blob = path.read_bytes()
            if b"lapack_" in blob:  # calls jaxlib's CPU LAPACK kernels: bind them first
                _bind_lapack()
            exported = export.deserialize(bytearray(blob))
            out_tree = pickle.loads(tree_path.read_bytes())
        except Exception as err:  # noqa: BLE001 - an unreadable entry is traced again
            log.warning("program cache: %s unreadable (%s); tracing again", path.name, err)
            exported = None
    if exported is None:
        trees: list = []
        try:
            exported = export.export(jax.jit(_flat(fn, in_tree, trees)))(*leaves)
            blob, out_tree = exported.serialize(), trees[-1]
            tree_blob = pickle.dumps(out_tree)
        except Exception as err:  # noqa: BLE001 - e.g. host callbacks: jit as before
            log.warning("program cache: jax.export cannot carry %s (%s)", _name_of(fn), err)
            return None
        atomic_write_bytes(tree_path, tree_blob)
        atomic_write_bytes(path, blob)
    lowered = jax.jit(exported.call).lower(*leaves)
    return _CachedLowered(lowered, out_tree)


@functools.cache
def _bind_lapack() -> None:
    """Have jaxlib bind its CPU LAPACK kernels, as it does when it lowers a linear-algebra op
    (here a 1 x 1 solve, lowered, not compiled). A program read from the cache is never
    lowered from Python, so without this its LAPACK calls (jnp.linalg.solve's getrf and trsm:
    discovery's fits) ran unbound in a process that had lowered none: a segmentation fault."""
    import jax.numpy as jnp

    one = np.ones((1, 1), np.float32)
    jax.jit(jnp.linalg.solve).lower(one, one[0])


class CompiledPrograms:
    """Compiled programs of one family (a trainer's evaluation, discovery's engine), one per
    signature: a name for the function and its static settings, and the arguments' structure,
    shapes and dtypes. Each is read from the program cache under `key` and its name where the
    cache is on and the family has a key (`program_key`; a later process deserializes it
    instead of tracing), else compiled by jax.jit. `get` compiles without calling, so that
    several threads can then call one program compiled once."""

    def __init__(self, key: str | None):
        self.key, self.compiled = key, {}

    def __call__(self, name: str, fn, *args):
        return self.get(name, fn, *args)(*args)

    def get(self, name: str, fn, *args):
        leaves, tree = jax.tree.flatten(args)
        signature = (name, tree, tuple((np.shape(x), np.result_type(x).str) for x in leaves))
        if signature not in self.compiled:
            self.compiled[signature] = self._compile(name, fn, args)
        return self.compiled[signature]

    def _compile(self, name: str, fn, args):
        return lowered_program(fn, args, self.key and f"{self.key}:{name}").compile()


def lowered_program(fn, args: tuple, key: str | None):
    """`fn` lowered for `args`: read from the program cache under `key` where the cache is on
    and the program has a key (`cached_lowering`), else traced by jax.jit. Either compiles
    with `.compile(compiler_options)`."""
    directory = program_cache_dir()
    if key and directory:
        cached = cached_lowering(fn, args, key, directory)
        if cached is not None:
            return cached
    return jax.jit(fn).lower(*args)


def _name_of(x) -> str:
    return f"{getattr(x, '__module__', '?')}.{getattr(x, '__qualname__', repr(x))}"


class _CachedLowered:
    def __init__(self, lowered, out_tree):
        self.lowered, self.out_tree = lowered, out_tree

    def compile(self, compiler_options: dict | None = None):
        return _Unflatten(self.lowered.compile(compiler_options), self.out_tree)
