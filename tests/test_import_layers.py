"""jaxdrive's layers hold: pyproject.toml's import-linter contracts pass on the package, fail on
a copy of it with one import pointing up, and the module graph (imports inside functions included)
has no cycle; no module imports another one's private names."""

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("importlinter")
grimp = pytest.importorskip("grimp")

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "jaxdrive"


def lint(root: Path):
    """``lint-imports`` (no cache) with ``root``'s pyproject.toml, on the ``jaxdrive`` under ``root``:
    its exit status and output. A fresh process, so that ``root``'s copy is the one imported."""
    code = (
        "import sys\nfrom importlinter.cli import lint_imports\n"
        "sys.exit(lint_imports(config_filename='pyproject.toml', no_cache=True, no_logo=True))\n"
    )
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(root), os.environ.get("PYTHONPATH", "")]),
        "COLUMNS": "200",
    }  # one line per contract and per import
    out = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, timeout=120)
    return out.returncode, out.stdout + out.stderr


def test_the_contracts_hold():
    status, out = lint(ROOT)
    assert status == 0, out
    assert "BROKEN" not in out and "0 broken" in out


def test_an_import_pointing_up_breaks_them(tmp_path):
    """jaxdrive.geometry (a bottom layer) importing the command line, as a planted module-level
    line: the layers contract must name it."""
    shutil.copytree(PACKAGE, tmp_path / "jaxdrive", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    assert lint(tmp_path)[0] == 0  # the copy itself is as clean as the package
    with open(tmp_path / "jaxdrive" / "geometry.py", "a") as f:
        f.write("\n\ndef _planted():\n    import jaxdrive.cli  # noqa: F401\n")
    status, out = lint(tmp_path)
    assert status != 0
    assert any(line.startswith("jaxdrive's layers") and line.endswith("BROKEN") for line in out.splitlines())
    assert "jaxdrive.geometry -> jaxdrive.cli" in out


def test_no_module_imports_itself_back():
    """No cycle in the module graph at all, package __init__ modules included (the contracts
    check cycles between siblings; a child importing its parent package's __init__ is not one)."""
    graph = grimp.build_graph("jaxdrive", cache_dir=None)
    edges = {m: graph.find_modules_directly_imported_by(m) for m in graph.modules}
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while not part or part[-1] != v:
                part.append(stack.pop())
                on_stack.discard(part[-1])
            if len(part) > 1:
                cycles.append(sorted(part))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(edges)))
    for m in sorted(edges):
        if m not in index:
            visit(m)
    assert cycles == []


def test_private_names_stay_in_their_modules():
    """``from jaxdrive.x import _name`` and ``x._name`` of an imported jaxdrive module: a private
    helper another module needs is public where it lives."""
    crossings = []
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        modules = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("jaxdrive"):
                for alias in node.names:
                    if alias.name.startswith("_") and not alias.name.startswith("__"):
                        crossings.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.module}.{alias.name}")
                    modules[alias.asname or alias.name] = node.module
            elif isinstance(node, ast.Import):
                modules.update({a.asname: a.name for a in node.names if a.asname and a.name.startswith("jaxdrive")})
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in modules
                and node.attr.startswith("_")
                and not node.attr.startswith("__")
            ):
                crossings.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.value.id}.{node.attr}")
    assert crossings == []
