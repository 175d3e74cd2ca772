"""The house's shape (issue 32): the library below, the commands above, no import circle.

The import graph is built from the source of the installed layout (``gpumap/``, ``sim/`` as
``gpumap.sim``, ``kernels/`` as ``gpumap.kernels``, ``bench/`` as ``gpumap.bench``), counting
every ``import``, module level or inside a function (a lazy import closes a circle just the
same). ``from gpumap import X`` counts as an import of the module that the package's lazy
``__getattr__`` loads for ``X``.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: installed name -> folder in the checkout
TREES = {"gpumap": ROOT / "gpumap", "gpumap.sim": ROOT / "sim", "gpumap.kernels": ROOT / "kernels",
         "gpumap.bench": ROOT / "bench"}
COMMANDS = "gpumap.commands"
#: what every command may share: the package's dispatcher and its common helpers
SHARED = {COMMANDS, f"{COMMANDS}.common", f"{COMMANDS}.__main__"}
MAX_LINES = 600
#: the map core's folder, and what it may import besides itself: the backends and the basics
CORE = "gpumap.core"
BASICS = {"gpumap.errors", "gpumap.spec", "gpumap.geometry", "gpumap.reference", "gpumap.pings",
          "gpumap.limits", "gpumap.atomic", "gpumap.memory", "gpumap.lie", "gpumap.kernels"}
MAX_TOP_MODULES = 12


def _modules() -> dict[str, Path]:
    mods = {}
    for base, folder in TREES.items():
        for p in folder.rglob("*.py"):
            if base == "gpumap" and p.relative_to(folder).parts[0] in ("sim", "kernels", "bench"):
                continue  # links made for a device run (the installed layout in a checkout)
            parts = p.relative_to(folder).with_suffix("").parts
            parts = parts[:-1] if parts[-1] == "__init__" else parts
            mods[".".join((base, *parts))] = p
    return mods


def _lazy_names(init: Path) -> dict[str, str]:
    """``gpumap.X`` -> the module ``gpumap.__getattr__`` imports for X (read from its source)."""
    out: dict[str, str] = {}
    fn = next(n for n in ast.parse(init.read_text()).body
              if isinstance(n, ast.FunctionDef) and n.name == "__getattr__")
    for node in ast.walk(fn):
        if isinstance(node, ast.If):
            names = [c.value for c in ast.walk(node.test) if isinstance(c, ast.Constant)]
            mods = [f"{n.module}.{a.name}" for n in node.body if isinstance(n, ast.ImportFrom)
                    and (n.module or "").startswith("gpumap") for a in n.names]
            mods += [c.value for n in node.body for c in ast.walk(n) if isinstance(c, ast.Constant)
                     and isinstance(c.value, str) and c.value.startswith("gpumap.")]
            for name in names:
                if isinstance(name, str) and mods:
                    out[f"gpumap.{name}"] = mods[0]
    return out


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    lazy = _lazy_names(TREES["gpumap"] / "__init__.py")
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
                n = lazy.get(n, n)
                if n.startswith("bench."):  # a checkout's `python -m bench` spelling
                    n = "gpumap." + n
                if n in mods and n != m and n != "gpumap":
                    g[m].add(n)
    return g


def _cycle(g: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``g`` (a list of modules, first == last), or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for n in sorted(g[m]):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state and (c := visit(n)):
                return c
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(g):
        if m not in state and (c := visit(m)):
            return c
    return None


def _is_command(m: str) -> bool:
    return m.startswith(COMMANDS + ".") and m not in SHARED


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return _graph()


def test_no_import_circle(graph) -> None:
    assert _cycle(graph) is None, " -> ".join(_cycle(graph) or [])


def test_the_circle_check_sees_a_circle() -> None:
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycle(g) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_the_graph_sees_lazy_and_package_imports(graph) -> None:
    # lazy imports inside functions count, and ``from gpumap import MinMaxMapper`` is the mapper
    assert "gpumap.io.octomap" in graph[f"{COMMANDS}.export"]
    assert "gpumap.core.mapper" in graph["gpumap.core.sparse"]
    lazy = _lazy_names(TREES["gpumap"] / "__init__.py")
    assert (
        lazy["gpumap.MinMaxMapper"] == "gpumap.core.mapper"
        and lazy["gpumap.refine_saved"] == "gpumap.layers.refine"
    )


def test_the_library_never_imports_a_command(graph) -> None:
    for m, deps in graph.items():
        if m.startswith(COMMANDS) or m.startswith("gpumap.bench"):
            continue
        above = sorted(d for d in deps if d.startswith(COMMANDS))
        assert not above, f"{m} (library) imports {above}: commands sit above the library"


def test_no_command_imports_another_command(graph) -> None:
    cmds = [m for m in graph if _is_command(m)]
    assert len(cmds) >= 10, cmds  # one module per subcommand
    for m in cmds:
        others = sorted(d for d in graph[m] if _is_command(d))
        assert not others, f"{m} imports the commands {others}: move what they share one floor down"


def test_every_subcommand_has_its_own_module() -> None:
    from gpumap.commands import COMMANDS as TABLE

    for name, (mod, _) in TABLE.items():
        assert (TREES["gpumap"] / "commands" / f"{mod}.py").is_file(), name


def _core_ok(dep: str) -> bool:
    return dep.startswith(CORE) or dep.startswith("gpumap.backends") or dep in BASICS \
        or dep.startswith("gpumap.kernels")


def test_the_core_imports_only_the_backends_and_the_basics(graph) -> None:
    core = [m for m in graph if m == CORE or m.startswith(CORE + ".")]
    assert len(core) >= 8, core
    for m in core:
        above = sorted(d for d in graph[m] if not _core_ok(d))
        assert not above, f"{m} (the map core) imports {above}: only the backends and the basics"


def test_the_core_check_sees_a_layer_import() -> None:
    assert not _core_ok("gpumap.layers.confidence") and not _core_ok("gpumap.pipeline.replay")
    assert not _core_ok("gpumap.viewer") and _core_ok("gpumap.backends.base") and _core_ok("gpumap.spec")


def test_the_basics_import_nothing_above_them(graph) -> None:
    for m in BASICS - {"gpumap.kernels"}:
        above = sorted(d for d in graph[m] if d not in BASICS and not d.startswith("gpumap.backends"))
        assert not above, f"{m} (a basic) imports {above}"


def test_the_library_never_imports_the_benchmarks_or_their_experiments(graph) -> None:
    for m, deps in graph.items():
        if m.startswith("gpumap.bench") or m.startswith(COMMANDS):
            continue
        assert not [d for d in deps if d.startswith("gpumap.bench")], m


def test_layers_and_drivers_sit_above_the_core(graph) -> None:
    for m, deps in graph.items():
        if m.startswith("gpumap.layers"):
            bad = sorted(d for d in deps if d.startswith(("gpumap.pipeline", "gpumap.viewer", "gpumap.ros",
                                                          COMMANDS)))
            assert not bad, f"{m} (a layer) imports {bad}"


def test_at_most_twelve_modules_directly_under_gpumap() -> None:
    top = sorted(p.name for p in (ROOT / "gpumap").glob("*.py"))
    assert len(top) <= MAX_TOP_MODULES, top


def test_the_mapper_takes_at_most_eight_parameters() -> None:
    import inspect

    from gpumap.core.mapper import MinMaxMapper

    params = [n for n in inspect.signature(MinMaxMapper.__init__).parameters if n != "self"]
    assert len(params) <= 8, params


def test_no_module_of_the_library_is_over_600_lines() -> None:
    long = {str(p.relative_to(ROOT)): n for p in (ROOT / "gpumap").rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"modules over {MAX_LINES} lines: {long}"


def test_importing_the_octomap_writer_loads_no_command() -> None:
    code = "import sys, gpumap.io.octomap; print(any(m.startswith('gpumap.commands') for m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
