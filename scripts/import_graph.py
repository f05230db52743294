"""The picture of the project's import graph in floors: docs/architecture-imports.svg.

    python3 scripts/import_graph.py [--out docs/architecture-imports.svg] [--depth 2] [PACKAGE ...]

Everything is derived from the code: every `import` of the packages (those inside functions too) is read
with `ast`; modules are grouped into nodes by the first `--depth` parts of their names (`service.routes.jobs`
-> `service.routes`); an import of a package's `__init__` counts as an import of the module that defines the
imported name. A node's floor is 0 when it imports no other node, else one above the highest floor it imports,
so every arrow points down. Nodes tied by an import cycle share a floor and are drawn in red, with the
arrows of the cycle. Plain SVG, no dependency.
"""

from __future__ import annotations

import argparse
import ast
from collections import defaultdict
from dataclasses import dataclass
from html import escape
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("estimation", "neural", "service")
OUT = ROOT / "docs" / "architecture-imports.svg"

NODE_WIDTH, NODE_HEIGHT, GAP_X, MARGIN, LABEL_WIDTH = 140, 26, 14, 30, 60
LINE_HEIGHT, FLOOR_GAP, PER_LINE = 40, 30, 10
COLOURS = {"estimation": "#dbe9f6", "neural": "#e3f1df", "service": "#fbe9d0"}
CYCLE_COLOUR = "#d62728"


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@dataclass(frozen=True)
class Module:
    name: str
    path: Path

    @property
    def is_package(self) -> bool:
        return self.path.name == "__init__.py"


def read_modules(root: Path, packages: list[str]) -> dict[str, Module]:
    modules = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            name = module_name(path, root)
            modules[name] = Module(name, path)
    return modules


def imports_of(module: Module, known: dict[str, Module]) -> list[tuple[str, str | None]]:
    """(imported module, imported name or None) for every import statement of the module."""
    tree = ast.parse(module.path.read_text(encoding="utf-8"), str(module.path))
    package = module.name if module.is_package else module.name.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, None) for alias in node.names if alias.name in known]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                if submodule in known:
                    found.append((submodule, None))
                elif base in known:
                    found.append((base, alias.name))
    return found


def defining_module(target: str, name: str | None, known: dict[str, Module], seen=frozenset()) -> str:
    """The module that defines `name`, following a package `__init__`'s re-exports."""
    module = known[target]
    if name is None or not module.is_package or target in seen:
        return target
    for imported, imported_name in imports_of(module, known):
        if imported_name == name:
            return defining_module(imported, name, known, seen | {target})
    return target


def node_of(module: str, depth: int) -> str:
    return ".".join(module.split(".")[:depth])


def module_graph(known: dict[str, Module]) -> dict[str, set[str]]:
    """Module -> the modules it imports; a package `__init__`'s own re-exports are not edges."""
    graph = {}
    for name, module in known.items():
        targets = set()
        if not module.is_package:
            for imported, imported_name in imports_of(module, known):
                target = defining_module(imported, imported_name, known)
                if target != name:
                    targets.add(target)
        graph[name] = targets
    return graph


def node_graph(modules: dict[str, set[str]], depth: int) -> dict[str, set[str]]:
    imported = {target for targets in modules.values() for target in targets}
    graph: dict[str, set[str]] = defaultdict(set)
    for module, targets in modules.items():
        if not targets and module not in imported and "." not in module:
            continue  # a top-level package whose __init__ only re-exports: not a node of its own
        source = node_of(module, depth)
        graph[source] |= {node_of(target, depth) for target in targets} - {source}
    for targets in list(graph.values()):
        for target in targets:
            graph.setdefault(target, set())
    return dict(graph)


def strongly_connected(graph: dict[str, set[str]]) -> dict[str, int]:
    """Node -> its component's index (Tarjan's algorithm, iterative)."""
    index, low, component, on_stack, stack, counter = {}, {}, {}, set(), [], 0
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component[member] = index[node]
                    if member == node:
                        break
    return component


def floors(graph: dict[str, set[str]], component: dict[str, int]) -> dict[str, int]:
    """Floor of each node: 0 for a node importing nothing, else one above the highest node it imports."""
    members = defaultdict(set)
    for node, c in component.items():
        members[c].add(node)
    floor_of_component: dict[int, int] = {}

    def floor(c: int) -> int:
        if c not in floor_of_component:
            below = {component[t] for m in members[c] for t in graph[m]} - {c}
            floor_of_component[c] = 1 + max((floor(b) for b in below), default=-1)
        return floor_of_component[c]

    return {node: floor(component[node]) for node in graph}


def render_svg(graph: dict[str, set[str]], depth: int) -> str:
    component = strongly_connected(graph)
    size = defaultdict(int)
    for c in component.values():
        size[c] += 1
    in_cycle = {node for node, c in component.items() if size[c] > 1}
    floor = floors(graph, component)
    top = max(floor.values(), default=0)
    packages = sorted({node.split(".")[0] for node in graph}, key=lambda p: (p not in PACKAGES, p))
    by_floor = defaultdict(list)
    first_of_component = {}
    for node in sorted(graph):
        first_of_component.setdefault(component[node], node)
    # members of one cycle side by side
    for node in sorted(
        graph, key=lambda n: (packages.index(n.split(".")[0]), first_of_component[component[n]], n)
    ):
        by_floor[floor[node]].append(node)
    lines = {level: -(-len(by_floor[level]) // PER_LINE) for level in range(top + 1)}
    width = MARGIN * 2 + LABEL_WIDTH + PER_LINE * (NODE_WIDTH + GAP_X)
    height = MARGIN * 2 + 40 + sum(lines.values()) * LINE_HEIGHT + top * FLOOR_GAP
    position, floor_y, y = {}, {}, MARGIN + 40
    for level in range(top, -1, -1):
        floor_y[level] = y
        for i, node in enumerate(by_floor[level]):
            in_line = min(PER_LINE, len(by_floor[level]) - i // PER_LINE * PER_LINE)
            offset = (PER_LINE - in_line) * (NODE_WIDTH + GAP_X) / 2
            position[node] = (
                MARGIN + LABEL_WIDTH + offset + i % PER_LINE * (NODE_WIDTH + GAP_X),
                y + i // PER_LINE * LINE_HEIGHT,
            )
        y += lines[level] * LINE_HEIGHT + FLOOR_GAP
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:.0f}" height="{height:.0f}" '
        f'viewBox="0 0 {width:.0f} {height:.0f}" font-family="sans-serif" font-size="11">',
        '<defs><marker id="arrow" viewBox="0 0 10 10" refX="10" refY="5" markerWidth="6" markerHeight="6" '
        'orient="auto-start-reverse"><path d="M 0 0 L 10 5 L 0 10 z" fill="#888"/></marker>'
        '<marker id="cycle" viewBox="0 0 10 10" refX="10" refY="5" markerWidth="6" markerHeight="6" '
        f'orient="auto-start-reverse"><path d="M 0 0 L 10 5 L 0 10 z" fill="{CYCLE_COLOUR}"/></marker>'
        "</defs>",
        f'<rect width="{width:.0f}" height="{height:.0f}" fill="white"/>',
    ]
    for level in range(top + 1):
        y = floor_y[level]
        out.append(f'<text x="{MARGIN}" y="{y + 17}" fill="#666">floor {level}</text>')
        out.append(
            f'<line x1="{MARGIN}" x2="{width - MARGIN}" y1="{y - FLOOR_GAP / 2 - 4:.0f}" '
            f'y2="{y - FLOOR_GAP / 2 - 4:.0f}" stroke="#eee"/>'
        )
    for i, package in enumerate(packages):
        x = MARGIN + LABEL_WIDTH + i * (NODE_WIDTH + GAP_X)
        out.append(
            f'<rect x="{x}" y="{MARGIN}" width="{NODE_WIDTH}" height="{NODE_HEIGHT}" rx="4" '
            f'fill="{COLOURS.get(package, "#eee")}" stroke="#555"/>'
        )
        out.append(
            f'<text x="{x + NODE_WIDTH / 2:.0f}" y="{MARGIN + 17}" text-anchor="middle" '
            f'font-weight="bold">{escape(package)}/</text>'
        )
    for source in sorted(graph):
        for target in sorted(graph[source]):
            cyclic = component[source] == component[target] and source in in_cycle
            (x1, y1), (x2, y2) = position[source], position[target]
            x1, x2 = x1 + NODE_WIDTH / 2, x2 + NODE_WIDTH / 2
            if y2 > y1:
                y1 += NODE_HEIGHT
            elif y2 < y1:
                y2 += NODE_HEIGHT
            else:  # a cycle within one line: side to side
                y1 = y2 = y1 + NODE_HEIGHT / 2
                side = NODE_WIDTH / 2 if x2 > x1 else -NODE_WIDTH / 2
                x1, x2 = x1 + side, x2 - side
            stroke = CYCLE_COLOUR if cyclic else "#999"
            opacity = 0.9 if cyclic else 0.35
            out.append(
                f'<line x1="{x1:.0f}" y1="{y1:.0f}" x2="{x2:.0f}" y2="{y2:.0f}" stroke="{stroke}" '
                f'stroke-opacity="{opacity}" marker-end="url(#{"cycle" if cyclic else "arrow"})"/>'
            )
    for node, (x, y) in sorted(position.items()):
        package = node.split(".")[0]
        label = node.partition(".")[2] or f"{node} (package)"
        stroke = CYCLE_COLOUR if node in in_cycle else "#555"
        out.append(
            f'<rect x="{x:.0f}" y="{y:.0f}" width="{NODE_WIDTH}" height="{NODE_HEIGHT}" rx="4" '
            f'fill="{COLOURS.get(package, "#eee")}" stroke="{stroke}" '
            f'stroke-width="{2 if node in in_cycle else 1}"><title>{escape(node)}</title></rect>'
        )
        out.append(
            f'<text x="{x + NODE_WIDTH / 2:.0f}" y="{y + 17:.0f}" text-anchor="middle">{escape(label)}</text>'
        )
    cycles = len({component[n] for n in in_cycle})
    note = (
        f"{len(graph)} nodes (modules grouped to depth {depth}); arrows point from importer to imported; "
        + (f"{cycles} import cycle(s) in red" if cycles else "no import cycle")
    )
    out.append(f'<text x="{MARGIN}" y="{height - 10:.0f}" fill="#666">{escape(note)}</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("packages", nargs="*", default=list(PACKAGES))
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--depth", type=int, default=2, help="module name parts that make one node")
    args = parser.parse_args()
    known = read_modules(ROOT, args.packages)
    graph = node_graph(module_graph(known), args.depth)
    args.out.write_text(render_svg(graph, args.depth))
    print(f"{args.out}: {len(graph)} nodes, {sum(map(len, graph.values()))} arrows")


if __name__ == "__main__":
    main()
