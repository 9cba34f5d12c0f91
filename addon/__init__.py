"""DIBR-GS Blender add-on: a thin bpy layer; the logic lives in dibrgs_core.

Import rule for ``dibrgs_core``: see ``addon/_core.py`` (the sibling package
of the extension, else the absolute one). Work that needs torch runs in
subprocesses of the training interpreter, see ``operators.py`` and
``setup.py``; batch mode is ``batch.py`` (``blender -b -c dibrgs ...``).
"""
from __future__ import annotations

import bpy

from . import batch, operators, panel, preferences, properties, setup

_CLASSES = (*preferences.CLASSES, *setup.CLASSES, *properties.CLASSES, *operators.CLASSES, *panel.CLASSES)
_cli_handle = None


def register() -> None:
    global _cli_handle
    for cls in _CLASSES:
        bpy.utils.register_class(cls)
    properties.register_props()
    for handlers, fn in operators.HANDLERS:
        if fn not in handlers:
            handlers.append(fn)
    if _cli_handle is None:
        _cli_handle = bpy.utils.register_cli_command(batch.CLI_COMMAND, batch.cli_command)


def unregister() -> None:
    global _cli_handle
    operators.stop_all(grace_s=5.0)
    setup.stop_all()
    if _cli_handle is not None:
        bpy.utils.unregister_cli_command(_cli_handle)
        _cli_handle = None
    for handlers, fn in operators.HANDLERS:
        if fn in handlers:
            handlers.remove(fn)
    properties.unregister_props()
    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
