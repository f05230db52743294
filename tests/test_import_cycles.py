"""The packages import downward only: no import cycle among the project's modules, counting the imports
made inside functions (they tie modules together just the same), and the service's floors (the
architecture page draws them) are imported only from above."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("estimation", "neural", "service")

SERVICE_FLOORS = [
    (
        "ground",
        [
            "kinds", "errors", "settings", "layout", "params", "pipeline", "auth", "openapi", "celery_config",
            "strict_json", "http_limits", "security_headers", "child_processes", "fair_queue", "loop_thread",
        ],
    ),
    ("store", ["store", "schemas"]),
    (
        "checks and housekeeping",
        ["uploads", "video_uploads", "validation", "webhooks", "housekeeping", "quotas"],
    ),
    ("how a job ends", ["job_end"]),
    ("running jobs", ["spread", "runner", "executor", "worker", "celery_app", "renders"]),
    ("actions", ["actions", "deps"]),
    ("scene supervisor", ["scene_supervisor"]),
    ("routes", ["routes"]),
    ("app", ["app"]),
    ("command line", ["commands", "cli"]),
]
"""The service's floors, bottom to top: a module imports modules of its own floor or below."""


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path, module: str, known: set[str]) -> set[str]:
    """The project modules `path` imports anywhere in it (package __init__ re-exports left out)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names if alias.name in known}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                target = f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base
                if target in known:
                    found.add(target)
    return found - {module}


def import_graph() -> dict[str, set[str]]:
    files = {module_name(p): p for package in PACKAGES for p in (ROOT / package).rglob("*.py")}
    known = set(files)
    return {
        module: {target for target in imports_of(path, module, known) if files[target].name != "__init__.py"}
        for module, path in files.items()
    }


def cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            for successor in successors:
                if successor not in index:
                    index[successor] = low[successor] = len(index)
                    stack.append(successor)
                    on_stack.add(successor)
                    work.append((successor, iter(sorted(graph[successor]))))
                    break
                if successor in on_stack:
                    low[node] = min(low[node], index[successor])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.add(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(component)
    return found


def test_the_cycle_finder_finds_a_cycle_hidden_in_a_function(tmp_path):
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [{"a", "b", "c"}]
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "one.py").write_text("def f():\n    from pkg.two import g\n")
    (package / "two.py").write_text("from . import one\n")
    known = {"pkg.one", "pkg.two"}
    assert imports_of(package / "one.py", "pkg.one", known) == {"pkg.two"}
    assert imports_of(package / "two.py", "pkg.two", known) == {"pkg.one"}


def test_no_module_of_the_packages_is_part_of_an_import_cycle():
    found = cycles(import_graph())
    assert found == [], "import cycles: " + "; ".join(" <-> ".join(sorted(c)) for c in found)


def test_only_the_app_imports_the_routes():
    graph = import_graph()
    importers = {
        module
        for module, targets in graph.items()
        if not module.startswith("service.routes") and any(t.startswith("service.routes") for t in targets)
    }
    assert importers == {"service.app"}


def service_floor(module: str) -> int | None:
    parts = module.split(".")
    if parts[0] != "service" or len(parts) < 2 or parts[1] == "migrations":
        return None
    return next(level for level, (_, packages) in enumerate(SERVICE_FLOORS) if parts[1] in packages)


def test_every_service_module_imports_only_its_floor_or_below():
    upward = [
        f"{module} ({SERVICE_FLOORS[service_floor(module)][0]}) -> {target} "
        f"({SERVICE_FLOORS[service_floor(target)][0]})"
        for module, targets in import_graph().items()
        if service_floor(module) is not None
        for target in targets
        if service_floor(target) is not None and service_floor(target) > service_floor(module)
    ]
    assert upward == []
