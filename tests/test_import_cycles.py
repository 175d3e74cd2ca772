"""No import cycle between the command line and the readers/writers (issue 24: cli <-> io.octomap).

The graph is built from the source (every ``import``, module level or inside a function,
since a lazy import closes a cycle just the same) and checked with a plain reachability search.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "gpumap"


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _graph() -> dict[str, set[str]]:
    mods = {_module_name(p): p for p in ROOT.rglob("*.py")}
    g: dict[str, set[str]] = {m: set() for m in mods}
    for m, p in mods.items():
        pkg = m if p.name == "__init__.py" else m.rpartition(".")[0]
        for node in ast.walk(ast.parse(p.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                names = [base] + [f"{base}.{a.name}" for a in node.names]
            for n in names:
                if n in mods and n != m:
                    g[m].add(n)
    return g


def _reaches(g: dict[str, set[str]], a: str, b: str) -> bool:
    seen, todo = {a}, [a]
    while todo:
        for n in g[todo.pop()]:
            if n == b:
                return True
            if n not in seen:
                seen.add(n)
                todo.append(n)
    return False


def test_io_never_imports_the_command_line():
    g = _graph()
    assert "gpumap.cli" in g and "gpumap.io.octomap" in g
    for m in g:
        if m.startswith("gpumap.io"):
            assert not _reaches(g, m, "gpumap.cli"), f"{m} imports gpumap.cli (directly or through others)"
    # and the check can see such an edge: the export command does import both
    assert _reaches(g, "gpumap.export_cli", "gpumap.cli")
    assert _reaches(g, "gpumap.export_cli", "gpumap.io.octomap")


def test_importing_the_octomap_writer_loads_no_cli():
    code = "import sys, gpumap.io.octomap; print('gpumap.cli' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
