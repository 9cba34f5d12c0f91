"""Add-on preferences: the training interpreter with "Set up / Check", default preset, local weights.

The interpreter is a Python 3.11 with torch and the library's dependencies (README,
section Blender, makes one with one command); ``setup.py`` checks it in the background.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import bpy
from bpy.props import EnumProperty, StringProperty

from . import setup
from ._core import ADDON_PACKAGE, jobs, train_config

PRESET_ITEMS = [(name, name.upper() if name == "cpu" else name.title(), text)
                for name, text in train_config.PRESET_SUMMARY.items()]


class DIBRGS_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON_PACKAGE

    python_path: StringProperty(
        name="Training Python", subtype="FILE_PATH",
        description="Python 3.11 with torch and the DIBR-GS dependencies, e.g. ~/dibrgs-env/bin/python "
                    "(README, section Blender). Empty: $DIBRGS_PYTHON, else Blender's own Python if it has torch")
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
        box = col.box()
        box.prop(self, "python_path")
        setup.draw_check(box, context)
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


CLASSES = (DIBRGS_AddonPreferences,)
