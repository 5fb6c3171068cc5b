"""The rules of the house that a machine can check: import boundaries and lazy imports."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_import_contracts_are_kept():
    exe = shutil.which("lint-imports")
    assert exe, "import-linter is a dev dependency: pip install -e .[dev]"
    out = subprocess.run([exe], cwd=ROOT, capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "0 broken" in out.stdout


def test_cli_startup_imports_no_heavy_library():
    code = (
        "import sys, app.cli as c; c.build_parser(); "
        "heavy = [m for m in ('torch', 'PySide6', 'pyqtgraph', 'cv2', 'harvesters', 'serial', "
        "'scipy', 'tifffile') if m in sys.modules]; print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "", f"imported at CLI start-up: {out.stdout.strip()}"


def _module_level_imports() -> dict[str, set[str]]:
    """Project module -> the project modules it imports at module level (not lazily)."""
    import ast

    files = [p for pkg in ("recon", "app", "drivers", "calibration")
             for p in (ROOT / pkg).rglob("*.py")]
    mods = {}
    for p in files:
        name = ".".join(p.relative_to(ROOT).with_suffix("").parts)
        mods[name.removesuffix(".__init__")] = p
    graph: dict[str, set[str]] = {}
    for name, p in mods.items():
        deps: set[str] = set()
        for node in ast.parse(p.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.Import):
                deps |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                deps |= {node.module} | {f"{node.module}.{a.name}" for a in node.names}
        graph[name] = {d for d in deps if d in mods and d != name}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while (w := stack.pop()) != v:
                comp.append(w)
            if comp:
                out.append([v, *comp])

    for v in graph:
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles_between_modules():
    graph = _module_level_imports()
    assert len(graph) > 100 and graph["recon.fista"], "the import graph was not read"
    toy = {"a": {"b"}, "b": {"a"}, "c": {"a"}}  # the detector itself finds a cycle
    assert [sorted(c) for c in _cycles(toy)] == [["a", "b"]]
    assert _cycles(graph) == []
