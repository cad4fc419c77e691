"""The layering of docs/architecture.md, checked on the source: no import cycles, the
library never imports the application layer, hardware and vision never import the
simulator, and imports inside functions are rare and say why."""

from __future__ import annotations

import ast
import os
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "jaxinertia"

#: Layers, lowest first: a module may import its own layer and the ones below it.
#: ``core`` is every top-level module of the package (robot, kinematics, ..., samples,
#: evaluation); ``virtual`` is a simulated servo bus, above both hardware and sim.
LAYERS = {
    "core": 0,
    "sim": 1,
    "hardware": 1,
    "vision": 1,
    "virtual": 2,
    "app": 3,
}
#: Packages of one layer that must not import each other.
APART = {("hardware", "sim"), ("vision", "sim"), ("sim", "hardware"), ("sim", "vision"),
         ("hardware", "vision"), ("vision", "hardware")}


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(path: Path, modules: dict[str, Path]) -> list[tuple[str, int, bool]]:
    """(imported jaxinertia module, line, inside a function) for every import."""
    tree = ast.parse(path.read_text())
    found = []

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef)
            names = []
            if isinstance(child, ast.Import):
                names = [a.name for a in child.names]
            elif isinstance(child, ast.ImportFrom) and child.module and child.level == 0:
                names = [child.module] + [f"{child.module}.{a.name}" for a in child.names]
            for name in names:
                if name.startswith("jaxinertia"):
                    while name not in modules and "." in name:
                        name = name.rsplit(".", 1)[0]
                    if name in modules:
                        found.append((name, child.lineno, inner))
            visit(child, inner)

    visit(tree, False)
    return found


def _layer(module: str) -> str:
    if module == "jaxinertia.__main__":  # ``python -m jaxinertia``: the command line
        return "app"
    parts = module.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in LAYERS) else "core"


@pytest.fixture(scope="module")
def graph():
    modules = _modules()
    return modules, {m: _imports(p, modules) for m, p in modules.items()}


def test_no_import_cycles(graph):
    modules, imports = graph
    edges = {m: sorted({t for t, _, _ in imps if t != m and not m.startswith(t + ".")
                        and t != "jaxinertia"}) for m, imps in imports.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(m):
        state[m] = 1
        stack.append(m)
        for t in edges[m]:
            if state.get(t) == 1:
                cycle = stack[stack.index(t):] + [t]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if t not in state:
                dfs(t)
        stack.pop()
        state[m] = 2

    for m in modules:
        if m not in state:
            dfs(m)


def test_layers_import_only_downwards(graph):
    _, imports = graph
    bad = []
    for m, imps in imports.items():
        src = _layer(m)
        for t, line, _ in imps:
            dst = _layer(t)
            if t == "jaxinertia":
                continue
            if LAYERS[dst] > LAYERS[src] or (src, dst) in APART:
                bad.append(f"{m}:{line} ({src}) imports {t} ({dst})")
    assert not bad, "imports against the layering:\n" + "\n".join(bad)


def test_imports_inside_functions_say_why(graph):
    """A local import (of the package or of a heavy optional dependency) carries a comment
    on its line or the line above saying why it is local."""
    modules, _ = graph
    bad = []
    for m, path in modules.items():
        lines = path.read_text().splitlines()
        tree = ast.parse(path.read_text())
        for fn in ast.walk(tree):
            if not isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            for node in ast.walk(fn):
                if isinstance(node, ast.Import | ast.ImportFrom):
                    here = lines[node.lineno - 1]
                    above = lines[node.lineno - 2] if node.lineno > 1 else ""
                    if "#" not in here and not above.strip().startswith("#") \
                            and "try:" not in above:
                        bad.append(f"{m}:{node.lineno}: {here.strip()}")
    assert not bad, "local imports without a reason:\n" + "\n".join(sorted(set(bad)))


def test_long_modules_state_why(graph):
    """Modules over 400 lines say at the top why they are one module."""
    modules, _ = graph
    long = []
    for m, path in modules.items():
        text = path.read_text()
        if text.count("\n") > 400:
            doc = ast.get_docstring(ast.parse(text)) or ""
            if "one module" not in doc.lower():
                long.append(f"{m}: {text.count(chr(10))} lines")
    assert not long, "long modules without a stated reason ('one module'):\n" + "\n".join(long)


def test_importing_the_package_runs_nothing():
    """``jaxinertia/__init__.py`` only imports and names (no call at module level: the
    XLA:CPU workaround is applied by the programs that start JAX, not on import)."""
    tree = ast.parse((PACKAGE / "__init__.py").read_text())
    # (the bodies of functions, such as the lazy names' module __getattr__, run when called)
    calls = [f"line {n.lineno}: {ast.unparse(n)}" for stmt in tree.body
             if not isinstance(stmt, ast.FunctionDef) for n in ast.walk(stmt)
             if isinstance(n, ast.Call)]
    assert not calls, "calls on import:\n" + "\n".join(calls)


def test_the_command_line_applies_the_xla_workarounds(monkeypatch, capsys):
    """``main()`` adds the XLA:CPU workaround to ``XLA_FLAGS`` before any command runs
    (and so before JAX starts); the processes it starts inherit it."""
    from jaxinertia._xla_workarounds import _CPU_FLAGS  # noqa: PLC0415 - the package under test
    from jaxinertia.app.cli import main  # noqa: PLC0415 - this file reads sources otherwise

    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.delenv("JAXINERTIA_KEEP_XLA_FLAGS", raising=False)
    assert main(["--help"]) == 0
    capsys.readouterr()
    assert all(f in os.environ["XLA_FLAGS"].split() for f in _CPU_FLAGS), os.environ["XLA_FLAGS"]
