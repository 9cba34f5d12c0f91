"""The repository loaded as Blender loads the extension: a package (``dibrgs_ext``) whose
``__init__`` hands off to ``addon/``; registered once a module, with a fresh empty scene a test."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def load_extension(name: str = "dibrgs_ext"):
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, REPO / "__init__.py",
                                                      submodule_search_locations=[str(REPO)])
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod
        spec.loader.exec_module(mod)
    return sys.modules[name]


@pytest.fixture(scope="module")
def ext():
    """The repository as an extension package, registered."""
    bpy = pytest.importorskip("bpy")
    mod = load_extension()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    mod.register()
    yield mod
    mod.unregister()


@pytest.fixture
def fresh(ext, tmp_path):
    """An empty scene whose run folder is in tmp_path."""
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.dibrgs.work_dir = str(tmp_path / "work")
    return scene
