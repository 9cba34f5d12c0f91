"""The package layout's rules, read from the code's own imports (docs/architecture.md)."""
from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
CORE = REPO / "dibrgs_core"
# Packages Blender's own Python imports: standard library and numpy only.
LIGHT = ("dibrgs_core.camera", "dibrgs_core.common", "dibrgs_core.bridge", "dibrgs_core.training.config",
         "dibrgs_core.models.config", "dibrgs_core.geometry.height_map")
HEAVY = {"torch", "PIL", "pycolmap", "scipy", "trimesh", "tifffile", "OpenEXR", "skimage", "transformers"}


def _modname(p: Path) -> str:
    parts = list(p.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(p: Path, name: str) -> list[tuple[str, str, bool]]:
    """(imported module, imported name, at module level) of every import in ``p``."""
    pkg = name if p.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(p.read_text())
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out += [(target, a.name, id(node) in top) for a in node.names]
        elif isinstance(node, ast.Import):
            out += [(a.name, "", id(node) in top) for a in node.names]
    return out


def _graph() -> tuple[dict[str, Path], dict[str, set[str]], list[str]]:
    mods = {_modname(p): p for p in CORE.rglob("*.py")}
    graph: dict[str, set[str]] = {m: set() for m in mods}
    private = []
    for m, p in mods.items():
        for target, name, _ in _imports(p, m):
            full = f"{target}.{name}"
            dest = full if full in mods else target
            if dest in mods and dest != m:
                graph[m].add(dest)
                if name.startswith("_") and dest == target:
                    private.append(f"{m} imports {name} from {target}")
    return mods, graph, private


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle_and_no_private_name_across_modules():
    _, graph, private = _graph()
    assert _cycles(graph) == []
    assert private == []


def test_render_and_models_never_import_training():
    mods, graph, _ = _graph()
    bad = [(m, d) for m, deps in graph.items() for d in deps
           if m.startswith(("dibrgs_core.render", "dibrgs_core.models")) and d.startswith("dibrgs_core.training")]
    assert bad == []


def test_bpy_only_in_synth_and_the_blender_layers():
    mods, _, _ = _graph()
    users = sorted(m for m, p in mods.items() if any(t.split(".")[0] in ("bpy", "mathutils")
                                                      for t, _, _ in _imports(p, m)))
    assert users and all(m.startswith("dibrgs_core.synth") for m in users), users


def test_blender_side_modules_load_without_heavy_libraries():
    """What the add-on imports in Blender's Python pulls in no torch, PIL, pycolmap, ... at import time."""
    mods, graph, _ = _graph()
    light = [m for m in mods if m.startswith(LIGHT)]
    seen, todo, heavy = set(), list(light), []
    while todo:
        m = todo.pop()
        if m in seen:
            continue
        seen.add(m)
        for target, _, top in _imports(mods[m], m):
            if not top:
                continue  # lazy imports run only when a function needs them
            if target.split(".")[0] in HEAVY:
                heavy.append(f"{m}: {target}")
            dest = target if target in mods else None
            if dest:
                todo.append(dest)
    assert heavy == []


def test_no_module_over_400_lines_but_the_documented_ones():
    allowed: set[str] = set()  # none today; docs/architecture.md names any exception
    long = {m for m, p in _graph()[0].items() if len(p.read_text().splitlines()) > 400}
    assert long <= allowed
    text = (REPO / "docs" / "architecture.md").read_text()
    assert all(f"`{m.replace('dibrgs_core.', '').replace('.', '/')}.py`" in text for m in long)
