"""The layers contract (docs/architecture.md, "Layers"): every import, lazy ones inside
functions and those under ``if TYPE_CHECKING:`` included, runs down the layers, and no
modules import each other in a circle."""

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"clflow": ROOT / "clflow", "clflow_cli": ROOT / "cli", "clflow_datasets": ROOT / "datasets_tools"}

#: bottom first; a room (a sub-package or a top-level module of clflow, or a package) imports
#: only rooms of lower layers. Rooms of one layer are independent of each other.
LAYERS = [
    ("clflow", "clflow.errors"),
    ("clflow.fileio", "clflow.limits", "clflow.materials", "clflow.regions", "clflow.runtime"),
    ("clflow.media", "clflow.environment", "clflow.splat", "clflow.query"),
    ("clflow.benchmark", "clflow.generate", "clflow.mpm", "clflow.flow", "clflow.peers"),
    ("clflow.parallel", "clflow.recon"),
    ("clflow.scene",),
    ("clflow.pipeline",),
    ("clflow.view", "clflow_datasets"),
    ("clflow.sweep",),
    ("clflow_cli",),
]
LAYER = {room: k for k, rooms in enumerate(LAYERS) for room in rooms}


def modules() -> dict[str, Path]:
    found = {}
    for package, base in PACKAGES.items():
        for path in base.rglob("*.py"):
            parts = [p for p in path.relative_to(base).with_suffix("").parts if p != "__init__"]
            found[".".join([package, *parts])] = path
    return found


def room(module: str) -> str:
    parts = module.split(".")
    return f"clflow.{parts[1]}" if parts[0] == "clflow" and len(parts) > 1 else parts[0]


def imports(modules: dict[str, Path]) -> set[tuple[str, str]]:
    """(importer, imported) pairs of the project's own modules: every import statement,
    those inside functions and under ``if TYPE_CHECKING:`` too (a circle of types is still a
    circle a reader has to follow)."""

    def resolve(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    edges = set()
    for module, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [resolve(a.name) for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [resolve(f"{node.module}.{a.name}") or resolve(node.module) for a in node.names]
            else:
                continue
            edges.update((module, t) for t in targets if t and t != module)
    return edges


def test_every_room_has_a_layer():
    rooms = {room(m) for m in modules()}
    assert sorted(rooms - set(LAYER)) == [], "place new packages in LAYERS (and docs/architecture.md)"


def test_imports_run_down_the_layers():
    found = modules()
    upward = sorted(
        f"{a} -> {b}"
        for a, b in imports(found)
        if room(a) != room(b) and LAYER.get(room(b), -1) >= LAYER.get(room(a), -1)
    )
    assert upward == []


def test_no_modules_import_each_other_in_a_circle():
    graph = defaultdict(set)
    for a, b in imports(modules()):
        graph[a].add(b)
    circles, index, low, stack, on_stack = [], {}, {}, [], set()

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    for v in list(graph):
        if v not in index:
            visit(v)
    assert circles == []
