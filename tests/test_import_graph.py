"""The package's import graph: the layers stay apart (no cycles between settings, sketches, cameras and models).

Every import counts, also those inside functions and under TYPE_CHECKING: a lazy import hides a cycle from
Python but not from a reader.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, Set

PACKAGE = Path(__file__).resolve().parents[1] / "sked_ns"


def import_graph() -> Dict[str, Set[str]]:
    """Module -> the sked_ns modules it imports anywhere in its source."""
    modules = {".".join(("sked_ns",) + path.relative_to(PACKAGE).with_suffix("").parts).removesuffix(".__init__"): path
               for path in PACKAGE.rglob("*.py")}
    graph = {}
    for name, path in modules.items():
        imported = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                imported.add(node.module)
                imported |= {f"{node.module}.{alias.name}" for alias in node.names}
        graph[name] = {module for module in imported if module in modules and module != name}
    return graph


def reachable(graph: Dict[str, Set[str]], start: str) -> Set[str]:
    seen, todo = set(), [start]
    while todo:
        for module in graph[todo.pop()]:
            if module not in seen:
                seen.add(module)
                todo.append(module)
    return seen


def test_the_graph_sees_every_kind_of_import():
    graph = import_graph()
    assert "sked_ns.sketches" in graph["sked_ns.edit_box"]  # top level
    assert "sked_ns.datamanager" in graph["sked_ns.edit"]  # inside a function
    assert "sked_ns.sketches" in graph["sked_ns.options"]  # under TYPE_CHECKING


def test_no_cycle_between_base_scene_and_the_models():
    graph = import_graph()
    assert "sked_ns.base_scene" not in reachable(graph, "sked_ns.base_scene")
    assert "sked_ns.core" not in reachable(graph, "sked_ns.base_scene")


def test_no_cycle_between_cameras_and_sketches():
    graph = import_graph()
    assert "sked_ns.cameras" not in reachable(graph, "sked_ns.cameras")
    assert "sked_ns.sketches" not in reachable(graph, "sked_ns.cameras")


def test_settings_and_the_representation_free_edit_import_no_model():
    graph = import_graph()
    models = {"sked_ns.core", "sked_ns.nerfacto_model", "sked_ns.ngp_model", "sked_ns.pipeline"}
    assert not reachable(graph, "sked_ns.options") & (models | {"sked_ns.base_scene", "sked_ns.edit"})
    assert not reachable(graph, "sked_ns.edit") & models
    assert "sked_ns.edit" not in reachable(graph, "sked_ns.edit")
