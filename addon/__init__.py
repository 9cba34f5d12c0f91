"""DIBR-GS Blender add-on: a thin bpy layer; the logic lives in dibrgs_core.

Import rule for ``dibrgs_core``: see ``addon/_core.py`` (the sibling package
of the extension, else the absolute one). Heavy work (torch) runs in
subprocesses, see ``operators.py``.
"""
from __future__ import annotations

import bpy

from . import operators, panel, preferences, properties

_CLASSES = (*preferences.CLASSES, *properties.CLASSES, *operators.CLASSES, *panel.CLASSES)


def register() -> None:
    for cls in _CLASSES:
        bpy.utils.register_class(cls)
    properties.register_props()


def unregister() -> None:
    job = operators.active_job()
    if job is not None and not job.runner.finished:
        job.runner.cancel(grace_s=5.0)
    properties.unregister_props()
    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
