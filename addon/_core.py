"""Which ``dibrgs_core`` the add-on uses, resolved once in one place.

One rule: the add-on uses the ``dibrgs_core`` that sits beside it.

* Installed as a Blender extension, the repository root is the extension
  package (``bl_ext.<repo>.dibrgs``) and ``dibrgs_core`` is its sibling
  subpackage: it is imported relative to that package, so an unrelated
  ``dibrgs_core`` on Blender's ``sys.path`` can never shadow the bundled one.
* Imported as a top-level ``addon`` package (``scripts/run.py``, with the
  repository root on ``sys.path``) there is no parent package and the
  absolute ``dibrgs_core`` is used, which is the same checkout.

Only numpy- or stdlib-only modules are imported here (``camera.*``, ``bridge.*``, the height
map, errors, the training presets); torch runs in subprocesses (``bridge.jobs``).
``tests/addon/test_blender_addon.py`` checks that the add-on imports and builds a scene with
torch, Pillow and pycolmap blocked.
"""
from __future__ import annotations

import importlib

_PARENT = __package__.rpartition(".")[0]  # "" when imported as top-level "addon"
CORE_PACKAGE = f"{_PARENT}.dibrgs_core" if _PARENT else "dibrgs_core"
#: The add-on's name for Blender (AddonPreferences.bl_idname): the package
#: Blender registered, i.e. the extension root, or "addon" when top-level.
ADDON_PACKAGE = _PARENT or __package__

pinhole = importlib.import_module(CORE_PACKAGE + ".camera.pinhole")
camera_blender = importlib.import_module(CORE_PACKAGE + ".camera.blender")
serialize = importlib.import_module(CORE_PACKAGE + ".camera.serialize")
path = importlib.import_module(CORE_PACKAGE + ".bridge.path")
progress = importlib.import_module(CORE_PACKAGE + ".bridge.progress")
compositor = importlib.import_module(CORE_PACKAGE + ".bridge.compositor")
jobs = importlib.import_module(CORE_PACKAGE + ".bridge.jobs")
reports = importlib.import_module(CORE_PACKAGE + ".bridge.reports")
geometry = importlib.import_module(CORE_PACKAGE + ".bridge.geometry")
describe = importlib.import_module(CORE_PACKAGE + ".bridge.describe")
imagesize = importlib.import_module(CORE_PACKAGE + ".bridge.imagesize")
checks = importlib.import_module(CORE_PACKAGE + ".bridge.checks")
errors = importlib.import_module(CORE_PACKAGE + ".common.errors")
height_map = importlib.import_module(CORE_PACKAGE + ".geometry.height_map")
train_config = importlib.import_module(CORE_PACKAGE + ".training.config")
split = importlib.import_module(CORE_PACKAGE + ".data.split")
