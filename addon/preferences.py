"""Add-on preferences: the training interpreter, default preset, local weights.

The interpreter must have torch and ``dibrgs_core``; left empty, the add-on
uses ``$DIBRGS_PYTHON`` if set, else Blender's own ``sys.executable`` when a
subprocess check (``-c "import torch, dibrgs_core"``) passes.
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass, field

import bpy
from bpy.props import EnumProperty, StringProperty

from ._core import ADDON_PACKAGE, jobs, train_config

PRESET_ITEMS = [(name, name.upper() if name == "cpu" else name.title(), text)
                for name, text in train_config.PRESET_SUMMARY.items()]

_checked: dict[str, tuple[bool, str]] = {}


def check_python(python: str, refresh: bool = False) -> tuple[bool, str]:
    """Cached :func:`dibrgs_core.bridge.jobs.check_interpreter`."""
    if refresh or python not in _checked:
        _checked[python] = jobs.check_interpreter(python)
    return _checked[python]


class DIBRGS_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    python_path: StringProperty(
        name="Python interpreter", subtype="FILE_PATH",
        description="Python with torch and dibrgs_core that runs training. Empty: $DIBRGS_PYTHON, "
                    "else Blender's own Python if it can import them")
    default_preset: EnumProperty(name="Default preset", items=PRESET_ITEMS, default="cpu")
    depth_model: StringProperty(name="Depth model folder", subtype="DIR_PATH",
                                description="Local Depth Anything V2 transformers folder (optional)")
    dino_resnet: StringProperty(name="DINO ResNet-50 weights", subtype="FILE_PATH",
                                description="Local .pth file (optional)")
    dino_vit: StringProperty(name="DINO ViT-B/8 weights", subtype="FILE_PATH",
                             description="Local .pth file (optional)")
    lpips: StringProperty(name="LPIPS weights", subtype="FILE_PATH", description="Local file (optional)")

    def draw(self, context: bpy.types.Context) -> None:
        col = self.layout.column()
        row = col.row(align=True)
        row.prop(self, "python_path")
        row.operator("dibrgs.check_python", text="", icon="CHECKMARK")
        col.prop(self, "default_preset")
        box = col.box()
        box.label(text="Local weights (optional; nothing is downloaded)")
        for name in ("depth_model", "dino_resnet", "dino_vit", "lpips"):
            box.prop(self, name)


@dataclass
class Settings:
    """The preferences as plain values (defaults when the add-on has no stored preferences)."""

    python_path: str = ""
    default_preset: str = "cpu"
    weights: "jobs.Weights" = field(default_factory=lambda: jobs.Weights())


def settings(context: bpy.types.Context | None = None) -> Settings:
    context = context or bpy.context
    addon = context.preferences.addons.get(ADDON_PACKAGE)
    prefs = getattr(addon, "preferences", None) if addon else None
    if prefs is None:
        return Settings()
    w = jobs.Weights(*(bpy.path.abspath(getattr(prefs, n)) if getattr(prefs, n) else None
                       for n in ("depth_model", "dino_resnet", "dino_vit", "lpips")))
    return Settings(python_path=bpy.path.abspath(prefs.python_path) if prefs.python_path else "",
                    default_preset=prefs.default_preset, weights=w)


def resolve_python(context: bpy.types.Context | None = None) -> tuple[str | None, str]:
    """(interpreter, message); interpreter is None when none is usable."""
    chosen = settings(context).python_path or os.environ.get("DIBRGS_PYTHON", "")
    if chosen:
        ok, msg = check_python(chosen)
        return (chosen if ok else None), msg
    ok, msg = check_python(sys.executable)
    if ok:
        return sys.executable, msg
    return None, (f"Blender's Python ({sys.executable}) cannot import torch and dibrgs_core: set a Python "
                  "interpreter that can in the DIBR-GS add-on preferences")


class DIBRGS_OT_check_python(bpy.types.Operator):
    """Check that the chosen Python interpreter can import torch and dibrgs_core"""

    bl_idname = "dibrgs.check_python"
    bl_label = "Check Python"

    def execute(self, context: bpy.types.Context) -> set[str]:
        _checked.clear()
        python, msg = resolve_python(context)
        self.report({"INFO"} if python else {"ERROR"}, msg)
        return {"FINISHED"} if python else {"CANCELLED"}


CLASSES = (DIBRGS_AddonPreferences, DIBRGS_OT_check_python)
