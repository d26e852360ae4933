"""The layout rules of docs/architecture.md, checked on the source (ast), so that they stay true:
no module over 800 lines, an ``__all__`` in every public module, no module using another module's underscore
names, and no import cycle between modules at import time."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = [ROOT / "sdfcodec", *sorted(p for p in (ROOT / "plugins").iterdir() if (p / "__init__.py").exists())]
MAX_LINES = 800
# private members of third-party objects that have no public equivalent (torch's in-place version counter,
# which the conformance suite reads to catch an in-place write of unchanged values)
FOREIGN_PRIVATE_OK = {"_version"}


def _modules() -> dict[str, Path]:
    """Dotted module name -> file, for the core package and every built-in plugin."""
    out = {}
    for pkg in PACKAGES:
        for f in sorted(pkg.rglob("*.py")):
            rel = f.relative_to(pkg.parent).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = f
    return out


MODULES = _modules()


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _resolve(module: str, is_pkg: bool, node: ast.ImportFrom) -> str:
    """The absolute module an ``ImportFrom`` names (relative imports resolved against ``module``)."""
    if not node.level:
        return node.module or ""
    base = module.split(".") if is_pkg else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def test_no_module_over_800_lines():
    long = {m: n for m, f in MODULES.items() if (n := len(f.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines (split them by job): {long}"


def test_public_modules_declare_all():
    missing = []
    for m, f in MODULES.items():
        if any(_is_private(p) for p in m.split(".")) or m.endswith("__main__"):
            continue
        tree = ast.parse(f.read_text())
        names = {t.id for n in tree.body if isinstance(n, (ast.Assign, ast.AugAssign, ast.AnnAssign))
                 for t in (n.targets if isinstance(n, ast.Assign) else [n.target]) if isinstance(t, ast.Name)}
        if "__all__" not in names:
            missing.append(m)
    assert not missing, f"public modules without __all__: {missing}"


def test_no_module_uses_another_modules_private_names():
    """``from X import _name`` and ``module._name`` across modules of the project; and ``obj._attr`` on an
    object other than self/cls where the module itself never defines ``_attr`` (a private member of a class
    that lives elsewhere)."""
    bad = []
    for m, f in MODULES.items():
        tree = ast.parse(f.read_text())
        is_pkg = f.name == "__init__.py"
        module_aliases = {}
        own = set()
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                own.add(node.name)
            elif (isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store)
                  and isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                own.add(node.attr)  # a member this module's own classes define
            elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                own.add(node.id)
            elif isinstance(node, ast.ImportFrom):
                src = _resolve(m, is_pkg, node)
                if not src.split(".")[0].startswith("sdfcodec"):
                    continue
                for a in node.names:
                    if _is_private(a.name) and f"{src}.{a.name}" not in MODULES:
                        bad.append(f"{f.relative_to(ROOT)}:{node.lineno} imports {a.name} from {src}")
                    if f"{src}.{a.name}" in MODULES:
                        module_aliases[a.asname or a.name] = f"{src}.{a.name}"
            elif isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0].startswith("sdfcodec") and a.asname:
                        module_aliases[a.asname] = a.name
        for node in ast.walk(tree):
            if not (isinstance(node, ast.Attribute) and _is_private(node.attr)):
                continue
            v = node.value
            if isinstance(v, ast.Name) and v.id in module_aliases:
                bad.append(f"{f.relative_to(ROOT)}:{node.lineno} uses {v.id}.{node.attr}")
            elif isinstance(v, ast.Name) and v.id in ("self", "cls"):
                continue
            elif isinstance(v, ast.Call) and isinstance(v.func, ast.Name) and v.func.id in ("super", "type"):
                continue
            elif node.attr not in own and node.attr not in FOREIGN_PRIVATE_OK:
                bad.append(f"{f.relative_to(ROOT)}:{node.lineno} uses .{node.attr}, a private member defined "
                           "in another module")
    assert not bad, "private names used across modules:\n" + "\n".join(bad)


def _import_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports at import time (module level, outside functions and
    ``if TYPE_CHECKING``). Imports of the root packages (``sdfcodec``) and of a module's own parent package
    are left out: a package's ``__init__`` re-exports its submodules by design."""
    graph = {}
    for m, f in MODULES.items():
        is_pkg = f.name == "__init__.py"
        deps = set()
        tree = ast.parse(f.read_text())
        body = [n for n in tree.body if not (isinstance(n, ast.If) and "TYPE_CHECKING" in ast.unparse(n.test))]
        for node in body:
            targets = []
            if isinstance(node, ast.ImportFrom):
                src = _resolve(m, is_pkg, node)
                targets = [f"{src}.{a.name}" if f"{src}.{a.name}" in MODULES else src for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            for t in targets:
                if t in MODULES and t != m and "." in t and not m.startswith(t + ".") and not t.startswith(m + "."):
                    deps.add(t)
        graph[m] = deps
    return graph


def test_no_import_cycles():
    graph = _import_graph()
    state, stack, cycles = {}, [], []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for d in sorted(graph.get(n, ())):
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d])
            elif d not in state:
                visit(d)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


@pytest.mark.parametrize("plugin", [p.name for p in PACKAGES[1:]])
def test_plugins_import_only_the_public_api(plugin):
    allowed = {"sdfcodec", "sdfcodec.errors", "sdfcodec.testing", "sdfcodec.plugin"}
    bad = []
    for m, f in MODULES.items():
        if m.split(".")[0] != plugin:
            continue
        for node in ast.walk(ast.parse(f.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module or ""]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            for n in names:
                if n.split(".")[0].startswith("sdfcodec") and n.split(".")[0] != plugin and n not in allowed:
                    bad.append(f"{f.relative_to(ROOT)}:{node.lineno} imports {n}")
    assert not bad, f"{plugin} reaches beyond the public API: {bad}"


#: Parameter names (exact, or the suffix after "_") that hold a type sdfcodec owns: they are annotated with it
#: (under ``if TYPE_CHECKING:`` where a run-time import would cycle), never ``Any``; a function named so (or
#: ending so) returns it, also never ``Any``. ``model`` is search's QueryModel, ``m`` a Map.
OWNED_NAMES = {"reader", "writer", "codec", "header", "map", "m", "store", "manifest", "placer", "dataset", "model"}


def _owned_any(source: str) -> list[str]:
    """``line name`` of every parameter or return annotated ``Any`` whose name says it holds an owned type."""
    def owned(name: str) -> bool:
        return name in OWNED_NAMES or name.rsplit("_", 1)[-1] in OWNED_NAMES - {"m", "model", "map"}

    found = []
    for fn in ast.walk(ast.parse(source)):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        a = fn.args
        for arg in [*a.posonlyargs, *a.args, *a.kwonlyargs]:
            if arg.annotation is not None and ast.unparse(arg.annotation) == "Any" and owned(arg.arg):
                found.append(f"{arg.lineno} {fn.name}({arg.arg})")
        if fn.returns is not None and ast.unparse(fn.returns) == "Any" and owned(fn.name.lstrip("_")):
            found.append(f"{fn.lineno} {fn.name} -> Any")
    return found


def test_no_any_for_a_type_the_package_owns():
    planted = "def check(reader: Any, n: int) -> None: ...\ndef load_codec(x: int) -> Any: ...\n"
    assert _owned_any(planted) == ["1 check(reader)", "2 load_codec -> Any"]  # the check can fail
    bad = [f"{f.relative_to(ROOT)}:{hit}" for f in MODULES.values() for hit in _owned_any(f.read_text())]
    assert not bad, f"Any where the type is sdfcodec's own (annotate it; TYPE_CHECKING import if it cycles): {bad}"
