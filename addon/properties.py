"""Scene properties of the add-on (``scene.dibrgs``) and what the panel shows."""
from __future__ import annotations

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty, FloatVectorProperty,
                       IntProperty, PointerProperty, StringProperty)

from ._core import jobs
from .preferences import PRESET_ITEMS

METHOD_ITEMS = [("dibrgs", "DIBR-GS", "The full method"),
                ("3dgs", "3DGS", "Vanilla 3D Gaussian Splatting baseline")]

# Blender keeps only pointers to dynamic enum strings: hold them here.
_result_items: list[tuple[str, str, str]] = []


class DIBRGS_Decision(bpy.types.PropertyGroup):
    """One stage decision from a report (``dibrgs_core.common.report``)."""

    stage: StringProperty()
    step: StringProperty()
    applied: BoolProperty()
    reason: StringProperty()


class DIBRGS_Metric(bpy.types.PropertyGroup):
    """A metric from ``WORK/metrics.json`` (``name`` is the key)."""

    value: FloatProperty()


class DIBRGS_Result(bpy.types.PropertyGroup):
    """A result image datablock shown in the compositor (``name`` is the image name)."""

    kind: StringProperty(description="heldout, pseudo, active or flythrough")


def _result_view_items(self, context):
    _result_items[:] = [(r.name, r.name, f"{r.kind} render") for r in self.results]
    return _result_items or [("NONE", "(no results)", "")]


def _result_view_update(self, context):
    from . import compositor  # late: compositor imports this module

    if self.result_view != "NONE":
        compositor.select(context.scene, self.result_view)


def _is_curve(self, obj) -> bool:
    return obj.type == "CURVE"


class DIBRGS_SceneSettings(bpy.types.PropertyGroup):
    scene_dir: StringProperty(name="Scene", subtype="DIR_PATH",
                              description="Scene folder: LEVIR-NVS, COLMAP, transforms.json, Metashape XML, "
                                          "OpenDroneMap, Meshroom, OpenMVG, Bundler or RealityCapture XMP")
    work_dir: StringProperty(name="Run folder", subtype="DIR_PATH",
                             description="Where training writes its checkpoint, logs and renders")
    scene_json: StringProperty(description="Name of the text datablock holding the imported scene description")
    reference_view: StringProperty(name="Reference view",
                                   description="View whose intrinsics the pseudo and fly-through cameras use")
    preset: EnumProperty(name="Preset", items=PRESET_ITEMS, default="cpu")
    method: EnumProperty(name="Method", items=METHOD_ITEMS, default="dibrgs")
    iterations: IntProperty(name="Iterations", default=0, min=0,
                            description="0: the preset's number of iterations")
    resolution_scale: FloatProperty(name="Resolution scale", default=0.0, min=0.0, max=jobs.MAX_RESOLUTION_SCALE,
                                    step=10, precision=2,
                                    description="scale of the photos for training and rendering (1: full "
                                                "size); 0: the preset's (cpu: long side at most 512 px)")
    resume: BoolProperty(name="Resume", default=False, description="Continue from the run folder's checkpoint")
    pseudo_count: IntProperty(name="Pseudo views", default=0, min=0, max=1000,
                              description="Number of pseudo views sampled along the path; 0: the preset's "
                                          "number (96 for cpu)")
    path_curve: PointerProperty(name="Path", type=bpy.types.Object, poll=_is_curve,
                                description="Curve the pseudo views and the fly-through follow")
    path_target: PointerProperty(name="Look at", type=bpy.types.Object,
                                 description="Object the pseudo and fly-through cameras look at; empty: they take "
                                             "the orientation of the nearest training cameras")
    scene_up: FloatVectorProperty(name="Up", size=3, default=(0.0, 0.0, 1.0),
                                  description="Scene up axis (from the cameras); appears up in pseudo views")
    fly_frames: IntProperty(name="Frames", default=48, min=2, max=10000,
                            description="Frames of the fly-through along the path")
    # Outcome of the last action. The running job itself is never stored here (a saved
    # file would bring back a job that no longer exists): see operators.running_job.
    message: StringProperty(description="Outcome of the last action")
    error: StringProperty(description="Last failure, with the log path")
    error_is_setup: BoolProperty(description="The last failure came from the training Python's set-up "
                                             "(cleared by a successful Set up / Check)")
    log_path: StringProperty(subtype="FILE_PATH")
    decisions: CollectionProperty(type=DIBRGS_Decision)
    metrics: CollectionProperty(type=DIBRGS_Metric)
    results: CollectionProperty(type=DIBRGS_Result)
    result_view: EnumProperty(name="View", items=_result_view_items, update=_result_view_update,
                              description="Result shown by the compositor output and Viewer")


CLASSES = (DIBRGS_Decision, DIBRGS_Metric, DIBRGS_Result, DIBRGS_SceneSettings)


def register_props() -> None:
    bpy.types.Scene.dibrgs = PointerProperty(type=DIBRGS_SceneSettings)


def unregister_props() -> None:
    del bpy.types.Scene.dibrgs
