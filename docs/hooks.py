"""MkDocs hook: the configuration reference, generated from the schemas (hds/config/schemas.py).

A page holding the line `<!-- config-reference -->` gets, in its place, one table per schema
(every key, its type, its default, what `check()` allows, and the comment the schema gives it),
read from the source with `ast`, so the reference cannot drift from the code and the build
imports nothing of hds (no JAX).
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "hds" / "config" / "schemas.py"
KINDS_SOURCE = ROOT / "hds" / "config" / "kinds.py"  # the simulator kinds, declared by name
CONF = ROOT / "hds" / "conf"
MARKER = "<!-- config-reference -->"


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER not in markdown:
        return markdown
    return markdown.replace(MARKER, render(SOURCE.read_text()))


def comments_by_line(text: str) -> dict[int, str]:
    found = {}
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type == tokenize.COMMENT:
            found[tok.start[0]] = tok.string.lstrip("#").strip()
    return found


def constants_of(source: str) -> dict[str, list]:
    """The schemas' module-level constants of literal value (DISCOVER_EFFECTS, ...), and
    `kinds.KINDS`: the names hds/config/kinds.py declares, so the reference shows values."""
    found = {}
    for node in ast.parse(source).body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1:
            try:
                found[ast.unparse(node.targets[0])] = list(ast.literal_eval(node.value))
            except (ValueError, TypeError):
                pass
    declared = [
        call.args[0].value
        for call in ast.walk(ast.parse(KINDS_SOURCE.read_text()))
        if isinstance(call, ast.Call)
        and ast.unparse(call.func) == "declare"
        and call.args
        and isinstance(call.args[0], ast.Constant)
    ]
    return found | {"kinds.KINDS": declared}


def literal(node: ast.expr, constants: dict[str, list]) -> str | None:
    """A literal, a constant or list(...)/tuple(...) of one, as the reference writes it."""
    if isinstance(node, ast.Call) and ast.unparse(node.func) in ("list", "tuple"):
        node = node.args[0] if len(node.args) == 1 else node
    if ast.unparse(node) in constants:
        return str(constants[ast.unparse(node)])
    try:
        value = ast.literal_eval(node)
    except ValueError:
        return None
    return str(list(value)) if isinstance(value, (list, tuple)) else None


def default_of(node: ast.expr | None, constants: dict[str, list] | None = None) -> str:
    if node is None:
        return "required"
    text = ast.unparse(node)
    if text == "MISSING":
        return "required"
    call = node if isinstance(node, ast.Call) else None
    if call and ast.unparse(call.func) in ("field", "_effects_field"):
        for kw in call.keywords:
            if kw.arg == "default_factory":
                value = kw.value.body if isinstance(kw.value, ast.Lambda) else kw.value
                if (shown := literal(value, constants or {})) is not None:
                    return shown
                name = ast.unparse(value)
                return {"list": "[]", "dict": "{}"}.get(name, f"{name.removesuffix('()')}()")
            if kw.arg == "default":
                return ast.unparse(kw.value)
        return "[]"  # _effects_field(): an empty list
    try:  # as YAML writes it: null, true, 'a' -> a
        value = ast.literal_eval(node)
    except ValueError:
        return text
    if value is None or isinstance(value, bool):
        return {None: "null", True: "true", False: "false"}[value]
    return value if isinstance(value, str) else text


def checks(cls: ast.ClassDef, constants: dict[str, list] | None = None) -> dict[str, str]:
    """What each key's check allows, from the `_one_of` / `_in_range` calls of `check()`."""
    allowed = {}
    for fn in cls.body:
        if not (isinstance(fn, ast.FunctionDef) and fn.name == "check"):
            continue
        for call in ast.walk(fn):
            if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Name)):
                continue
            if not call.args or not isinstance(call.args[0], ast.Constant):
                continue
            key = str(call.args[0].value).split(".")[-1]
            args = [literal(a, constants or {}) or ast.unparse(a) for a in call.args[2:]]
            if call.func.id == "_one_of" and args:
                allowed[key] = f"one of {args[0]}"
            elif call.func.id == "_in_range" and args:
                upper = args[1] if len(args) > 1 else "inf"
                allowed[key] = f"[{args[0]}, {upper}]".replace('float("inf")', "inf")
    return allowed


def fields(cls: ast.ClassDef, comments: dict[int, str], constants: dict[str, list]):
    for stmt in cls.body:
        if not (isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name)):
            continue
        above, line = [], stmt.lineno - 1
        while line in comments and line not in {s.lineno for s in cls.body}:
            above.insert(0, comments[line])
            line -= 1
        text = " ".join([*above, comments.get(stmt.end_lineno, "")]).strip()
        default = default_of(stmt.value, constants)
        yield stmt.target.id, ast.unparse(stmt.annotation), default, text


def schema_of(annotation: str, classes) -> tuple[str, str] | None:
    """(schema, suffix) of a field whose type is a schema: EnvConfig, list[...], dict[...]."""
    for name in re.findall(r"\w+", annotation):
        if name in classes:
            if annotation.startswith("list"):
                return name, "[i]"
            if annotation.startswith("dict"):
                return name, ".<name>"
            return name, ""
    return None


def cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render(source: str) -> str:
    tree = ast.parse(source)
    comments = comments_by_line(source)
    constants = constants_of(source)
    classes = {
        node.name: node
        for node in tree.body
        if isinstance(node, ast.ClassDef)
        and any(ast.unparse(d) == "dataclass" for d in node.decorator_list)
    }
    out = []

    def visit(name: str, path: str) -> None:
        if path.endswith(".<name>"):  # a dict of a schema documented under its own group
            out.append(f"## `{path}` ({name})\n")
            out.append(f"Each entry takes the keys of a `{name}`, as documented above.\n")
            return
        cls = classes[name]
        doc = ast.get_docstring(cls)
        group = path.split(".")[0].split("[")[0]
        title = f"`{path}`" if path else "Top-level keys"
        out.append(f"## {title} ({name})\n")
        if doc:
            out.append(doc.split("\n\n")[0].replace("\n", " ") + "\n")
        options = sorted(p.stem for p in (CONF / group).glob("*.yaml")) if group else []
        if options and path == group:
            out.append("Presets (`" + group + "=`): " + ", ".join(f"`{o}`" for o in options) + "\n")
        allowed = checks(cls, constants)
        rows, nested = [], []
        for key, annotation, default, text in fields(cls, comments, constants):
            inner = schema_of(annotation, classes)
            dotted = f"{path}.{key}" if path else key
            if inner:
                nested.append((inner[0], dotted + inner[1]))
                if inner[1]:  # a list or dict of schemas: its row says so
                    text = text or f"entries of {inner[0]}"
                else:
                    continue
            rows.append(
                f"| `{dotted}` | `{cell(annotation)}` | `{cell(default)}` | "
                f"{cell(allowed.get(key, ''))} | {cell(text)} |"
            )
        if rows:
            out.append("| key | type | default | allowed | what |")
            out.append("| --- | --- | --- | --- | --- |")
            out.extend(rows)
            out.append("")
        for inner, dotted in nested:
            visit(inner, dotted)

    visit("Config", "")
    app = classes.get("DiscoverAppConfig")
    if app is not None:
        out.append("## `python -m hds.discover`'s own keys (DiscoverAppConfig)\n")
        out.append("Every key above, and:\n")
        out.append("| key | type | default | allowed | what |")
        out.append("| --- | --- | --- | --- | --- |")
        for key, annotation, default, text in fields(app, comments, constants):
            out.append(f"| `{key}` | `{cell(annotation)}` | `{cell(default)}` | | {cell(text)} |")
        out.append("")
        visit("EmpsConfig", "emps")
    return "\n".join(out)
