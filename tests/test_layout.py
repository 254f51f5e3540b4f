"""The house's layout as rules that can fail: the method imports nothing that measures it or
serves it, no module imports itself back through others, and no module of the method or the
service grows past a few hundred lines."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("estimator", "evaluation", "service", "sim", "cli", "bench", "clients")
MAX_LINES = 600


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(("posefuse", *parts))


def _modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            out[_module_name(path)] = path
    return out


def _imports(path: Path, top_level_only: bool) -> set[str]:
    """The posefuse modules a file imports (``from a import b`` counts ``a.b`` when that is a
    module); with ``top_level_only``, those run at import time, not inside functions."""
    tree = ast.parse(path.read_text(), filename=str(path))
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    out = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("posefuse")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.startswith("posefuse"):
                out.add(node.module)
                out |= {f"{node.module}.{a.name}" for a in node.names}
    return out


def _graph(top_level_only: bool) -> dict[str, set[str]]:
    modules = _modules()
    return {
        name: {m for m in _imports(path, top_level_only) if m in modules and m != name}
        for name, path in modules.items()
    }


def test_the_method_imports_nothing_that_measures_or_serves_it():
    forbidden = tuple(f"posefuse.{p}" for p in ("evaluation", "service", "sim", "cli", "bench"))
    third_party = ("zenoh", "fastapi", "mcap", "uvicorn", "starlette", "torch")
    offenders = []
    for name, path in _modules().items():
        if not name.startswith("posefuse.estimator"):
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            for n in names:
                if n.startswith(forbidden) or n.split(".")[0] in third_party:
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {n}")
    assert not offenders, "\n".join(offenders)


@pytest.mark.parametrize(
    ("package", "forbidden"),
    [
        ("evaluation", ("service", "cli", "bench", "clients")),
        ("service", ("cli", "bench", "clients")),
    ],
)
def test_the_measuring_and_the_service_stay_below_the_tools(package, forbidden):
    """evaluation/ measures the method without the service; service/ never reaches for the
    command line, the benchmarks or the clients."""
    offenders = [
        f"{name} imports {m}"
        for name, path in _modules().items()
        if name.startswith(f"posefuse.{package}")
        for m in sorted(_imports(path, top_level_only=False))
        if m.startswith(tuple(f"posefuse.{f}" for f in forbidden))
    ]
    assert not offenders, "\n".join(offenders)


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle, as the list of modules around it, or None (depth-first search)."""
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


@pytest.mark.parametrize("top_level_only", [True, False], ids=["at-import", "anywhere"])
def test_no_import_cycle(top_level_only):
    graph = _graph(top_level_only)
    # a package's __init__ re-exporting its own modules is not a cycle of the design
    for name in graph:
        graph[name] = {m for m in graph[name] if not name.startswith(m + ".")}
    cycle = _cycle(graph)
    assert cycle is None, " -> ".join(cycle)


def test_the_cycle_finder_finds_a_cycle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None


@pytest.mark.parametrize("package", ["estimator", "service"])
def test_modules_stay_a_few_hundred_lines(package):
    long = {
        str(p.relative_to(ROOT)): n
        for p in sorted((ROOT / package).rglob("*.py"))
        if (n := len(p.read_text().splitlines())) > MAX_LINES
    }
    assert not long, f"over {MAX_LINES} lines: {long}"


def test_tests_follow_the_tree():
    """A module's tests are found from its path: every folder of tests/ mirrors a package
    folder (tests/estimator/translation/ for estimator/translation/, ...)."""
    tests = ROOT / "tests"
    folders = [
        p.relative_to(tests)
        for p in sorted(tests.rglob("*"))
        if p.is_dir() and any(p.glob("test_*.py"))
    ]
    assert folders, "no test folders"
    strays = [str(f) for f in folders if str(f) != "." and not (ROOT / f).is_dir()]
    assert not strays, f"test folders with no package folder beside them: {strays}"
