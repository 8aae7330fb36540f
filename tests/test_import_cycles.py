"""No import cycles between project files, imports inside functions included.

A cycle makes a module's meaning depend on which of its partners happened to be imported
first, and hides a dependency behind a function-level import; the code digest's closure would
still be right, but the design would not. The graph is read from the source with the same
scanner the code digest uses (``pipeline.codedigest.SourceGraph``).
"""

from __future__ import annotations

from pathlib import Path

from pipeline.codedigest import SourceGraph

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "stages", "scene", "hardware", "avatar", "benchmarks")


def _project_files(graph: SourceGraph) -> list[Path]:
    return sorted(p.resolve() for top in PACKAGES for p in (graph.root / top).rglob("*.py")
                  if "__pycache__" not in p.parts)


def strongly_connected(edges: dict[Path, list[Path]]) -> list[list[Path]]:
    """Tarjan's components of more than one node (iterative: the graph may be deep)."""
    index: dict[Path, int] = {}
    low: dict[Path, int] = {}
    on_stack: set[Path] = set()
    stack: list[Path] = []
    components: list[list[Path]] = []
    counter = 0
    for start in edges:
        if start in index:
            continue
        work = [(start, iter(edges.get(start, ())))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            advanced = False
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(edges.get(child, ()))))
                    advanced = True
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            if advanced:
                continue
            work.pop()
            if work:
                parent = work[-1][0]
                low[parent] = min(low[parent], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    components.append(component)
    return components


def test_the_cycle_finder_finds_cycles() -> None:
    a, b, c, d = (Path(x) for x in "abcd")
    found = strongly_connected({a: [b], b: [c], c: [a], d: [a]})
    assert [sorted(map(str, comp)) for comp in found] == [["a", "b", "c"]]
    assert strongly_connected({a: [b], b: [c], c: [], d: [a]}) == []


def test_no_import_cycles_between_project_files() -> None:
    graph = SourceGraph(REPO)
    files = _project_files(graph)
    assert len(files) > 150
    edges = {path: graph.imported_files(path) for path in files}
    cycles = [sorted(graph.relpath(p) for p in comp) for comp in strongly_connected(edges)]
    assert cycles == [], "import cycles (break each by moving what both need into a module of its own): " + \
        "; ".join(" <-> ".join(cycle) for cycle in cycles)


def _package(rel: str) -> str:
    """The package a file belongs to: ``stages.<name>`` and ``hardware.<name>`` count on their own."""
    parts = rel.split("/")
    if parts[0] in ("stages", "hardware") and len(parts) > 2:
        return f"{parts[0]}.{parts[1]}"
    return parts[0]


def _package_edges(graph: SourceGraph) -> dict[str, set[str]]:
    edges: dict[str, set[str]] = {}
    for path in _project_files(graph):
        source = _package(graph.relpath(path))
        for target in graph.imported_files(path):
            other = _package(graph.relpath(target))
            if other != source:
                edges.setdefault(source, set()).add(other)
    return edges


def test_no_import_cycles_between_packages() -> None:
    """Each stage package (``stages.relight``, ``stages.evaluate``, ...) and each top-level package
    depends on others in one direction only."""
    edges = _package_edges(SourceGraph(REPO))
    as_paths = {Path(a): [Path(b) for b in sorted(bs)] for a, bs in edges.items()}
    cycles = [sorted(str(p) for p in comp) for comp in strongly_connected(as_paths)]
    assert cycles == [], "package cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_the_orchestrator_and_the_shared_vocabulary_import_no_stage() -> None:
    edges = _package_edges(SourceGraph(REPO))
    assert edges.get("pipeline", set()) == set(), "pipeline/ must know nothing of faces or stages"
    assert edges.get("scene", set()) == set()
    assert not any(dep.startswith("stages") for dep in edges.get("avatar", set()) | edges.get("hardware.studio", set()))


def test_no_project_module_imports_the_test_helpers() -> None:
    """``pipeline.testing`` is for tests; benchmarks and stages run a stage alone through
    ``pipeline.scratch`` or call the stage's own functions."""
    graph = SourceGraph(REPO)
    helpers = (REPO / "pipeline" / "testing.py").resolve()
    importers = [graph.relpath(p) for p in _project_files(graph) if helpers in graph.imported_files(p)]
    assert importers == [], f"import pipeline.testing (a test helper): {importers}"
