"""The layering of hds/ and bench/: modules call downward only, and no imports form a circle.

The layers, bottom first, are declared below as groups of modules; a module may import its own
layer and the layers beneath it. Imports are read from the source with `ast` (those inside
functions too: a deferred import is still a dependency), so the check needs nothing imported.
A new module must be placed in a layer (the first test says where it is missing). What breaks
the rule today and is not yet fixed is listed in KNOWN_VIOLATIONS with the reason: the debt,
stated, so that the test passes and a new violation still fails it.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# bottom first; a module belongs to the group of its longest matching prefix
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    # plumbing that knows no domain: files, the runtime, shuffling, quiet imports, parsing
    ("utils", ("hds.utils",)),
    # the physical effects: their laws, parameters and registry
    ("effects", ("hds.effects",)),
    # the simulators and plants, and the building blocks of a trainer (networks, noise, steps)
    (
        "simulation",
        (
            "hds.envs",
            "hds.real",
            "hds.networks",
            "hds.noise",
            "hds.anneal",
            "hds.animate",
            "hds.render",
        ),
    ),
    # the schemas of every config group (hds.config.schemas), their validation (.validation,
    # and .model: the MJCF and the device's memory), composing and loading (.composition)
    ("config", ("hds.config", "hds.conf")),
    # what an experiment is made of: data, the trainer, learned models, gap discovery,
    # evaluation, checkpoints, logging, figures, run directories
    (
        "methods",
        (
            "hds.data",
            "hds.algo",
            "hds.dynamics",
            "hds.discover",
            "hds.gap",
            "hds.results",  # the typed rows and summaries every writer and reader shares
            "hds.checkpoint",
            "hds.logger",
            "hds.plots",
            "hds.rundir",
            "hds.story",
            "hds.simulators",  # the registry of what a method trains on
            "hds.policy_store",  # a trained batch of policies as its own artefact
        ),
    ),
    # the experiment layer every tool calls, and saved policies
    ("experiment", ("hds.experiment", "hds.policy", "hds.numpy_policy", "hds.onnx_policy")),
    # the command-line tools
    (
        "commands",
        (
            "hds.run",
            "hds.loop",
            "hds.evaluate",
            "hds.export",
            "hds.report",
            "hds.discover.__main__",
            "hds.dynamics.__main__",
            "hds.commands",
            "hds.callbacks",  # Hydra's callbacks of the commands: the sweep's report at its end
        ),
    ),
    # the package's lazy API (`hds.train`, `hds.load_policy`, ...)
    ("api", ("hds",)),
    # the benchmarks, over everything
    ("bench", ("bench",)),
]

# (importer, imported): the debt, each with its reason and its fix. Remove an entry once fixed
# (the last test fails on an entry that no longer occurs, so the list cannot go stale).
KNOWN_VIOLATIONS: dict[tuple[str, str], str] = {}


def modules() -> dict[str, Path]:
    found = {}
    for package in ("hds", "bench"):
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join(parts)] = path
    return found


def imports(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The modules of hds/ and bench/ that `name` imports, anywhere in its source."""

    def owner(dotted: str) -> str | None:  # the module a dotted name lives in
        while dotted and dotted not in known:
            dotted = dotted.rpartition(".")[0]
        return dotted or None

    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [owner(alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package, up level - 1
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*up, base] if base else up)
            # `from pkg import sub` depends on the submodule; `from mod import name` on mod
            targets = [
                f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else owner(base)
                for alias in node.names
            ]
        else:
            continue
        found |= {t for t in targets if t and t != name}
    return found


def layer_of(name: str) -> int | None:
    best, best_len = None, -1
    for index, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            matches = name == prefix or (name.startswith(prefix + ".") and prefix != "hds")
            if matches and len(prefix) > best_len:
                best, best_len = index, len(prefix)
    return best


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: imports(name, path, known) for name, path in known.items()}


def upward_imports(edges: dict[str, set[str]]) -> set[tuple[str, str]]:
    return {
        (a, b)
        for a, targets in edges.items()
        for b in targets
        if layer_of(b) is not None and layer_of(a) is not None and layer_of(b) > layer_of(a)
    }


def circles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


def test_every_module_of_hds_and_bench_has_a_layer():
    unplaced = [name for name in modules() if layer_of(name) is None]
    assert not unplaced, f"place these modules in a layer of tests/test_layers.py: {unplaced}"


def test_no_module_imports_a_layer_above_its_own():
    upward = upward_imports(graph()) - set(KNOWN_VIOLATIONS)
    names = [name for name, _ in LAYERS]
    lines = [
        f"{a} ({names[layer_of(a)]}) imports {b} ({names[layer_of(b)]})" for a, b in sorted(upward)
    ]
    assert not lines, "upward imports:\n" + "\n".join(lines)


def test_no_imports_form_a_circle():
    found = circles(graph())
    assert not found, f"import circles: {found}"


def test_no_module_imports_another_modules_private_names():
    edges, known, private = graph(), modules(), []
    for name, path in known.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] in (
                "hds",
                "bench",
            ):
                private += [
                    f"{name}: from {node.module} import {a.name}"
                    for a in node.names
                    if a.name.startswith("_") and not a.name.startswith("__")
                ]
    assert edges and not private, "private names used across modules:\n" + "\n".join(private)


def test_the_known_violations_still_occur():
    """An entry fixed but left in KNOWN_VIOLATIONS would hide its return: remove it."""
    stale = set(KNOWN_VIOLATIONS) - upward_imports(graph())
    assert not stale, f"fixed, remove from KNOWN_VIOLATIONS: {sorted(stale)}"


def test_the_check_finds_an_upward_import_and_a_circle():
    """The checks themselves, on a made-up graph: utils importing the experiment is upward, and
    two modules importing each other are a circle."""
    edges = {"hds.utils.io": {"hds.experiment"}, "hds.experiment": {"hds.utils.io"}}
    assert upward_imports(edges) == {("hds.utils.io", "hds.experiment")}
    assert circles(edges) == [["hds.experiment", "hds.utils.io"]]
    assert circles({"hds.a": {"hds.b"}, "hds.b": set()}) == []
