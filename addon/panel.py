"""The "Train DIBR-GS" panel in the 3D viewport sidebar (N panel, tab "DIBR-GS").

Buttons are enabled by their operators' ``poll()``; when one cannot run, the
reason (``operators.why_not``) is shown under it. While a job runs, the fields
it was started with are locked and its progress comes from the runner in
memory (never from the file).
"""
from __future__ import annotations

import bpy

from . import scene_build, setup
from .operators import job_progress, running_job, why_not


def _reason(layout, context, action: str, shown: set[str]) -> None:
    """The reason ``action`` cannot run, unless an earlier box already said it."""
    reason = why_not(context, action)
    if reason and reason not in shown:
        shown.add(reason)
        layout.label(text=reason, icon="INFO")


class DIBRGS_PT_main(bpy.types.Panel):
    bl_label = "Train DIBR-GS"
    bl_idname = "DIBRGS_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "DIBR-GS"

    def draw(self, context):
        layout = self.layout
        props = context.scene.dibrgs
        job = running_job()
        locked = job is not None
        shown: set[str] = set()

        box = layout.box()
        box.label(text="Scene", icon="OUTLINER_OB_CAMERA")
        col = box.column()
        col.enabled = not locked
        col.prop(props, "scene_dir")
        op = col.operator("dibrgs.import_scene", icon="IMPORT")
        op.directory = props.scene_dir
        if scene_build.SCENE_TEXT in bpy.data.texts:  # move view cameras between the collections to change it
            try:
                col.label(text=scene_build.split_summary(), icon="OUTLINER_COLLECTION")
            except (ValueError, KeyError, TypeError):  # the stored description was edited by hand
                col.label(text="Split: the imported description is damaged; import again", icon="ERROR")
        col.prop(props, "work_dir")

        box = layout.box()
        box.label(text="Initialise", icon="POINTCLOUD_DATA")
        box.operator("dibrgs.initialise", icon="PLAY")
        if not locked:
            _reason(box, context, "initialise", shown)
        if props.decisions:
            col = box.column(align=True)
            for d in props.decisions:
                r = col.row()
                r.label(text=f"{d.stage}: {d.step}", icon="CHECKMARK" if d.applied else "X")
                r.label(text=d.reason)

        box = layout.box()
        box.label(text="Pseudo-view path", icon="CURVE_BEZCIRCLE")
        box.prop(props, "path_curve")
        box.prop(props, "path_target")
        row = box.row()
        row.enabled = not locked
        row.prop(props, "pseudo_count")
        box.operator("dibrgs.reset_path", icon="FILE_REFRESH")
        if props.path_curve is not None:
            if scene_build.path_edited(context, update=False):
                box.label(text="Edited: training uses its cameras", icon="INFO")
            else:
                kind = props.path_curve.get(scene_build.TRAJECTORY_KEY, "")
                box.label(text=f"As drawn: training samples the {kind}", icon="INFO")

        box = layout.box()
        box.label(text="Train", icon="SHADERFX")
        col = box.column()
        col.enabled = not locked
        col.prop(props, "preset")
        col.prop(props, "method")
        col.prop(props, "iterations")
        col.prop(props, "resolution_scale")
        col.prop(props, "resume")
        if job is not None:
            fraction, text = job_progress(job)
            box.progress(factor=fraction, type="BAR", text=text)
            box.operator("dibrgs.cancel", icon="CANCEL")
        else:
            box.operator("dibrgs.train", icon="PLAY")
            _reason(box, context, "train", shown)
        python, _ = setup.chosen_python(context)
        run = setup.latest(python)
        if run is not None and run.running:
            box.progress(factor=run.report.fraction, type="BAR", text="Set up / Check: " + run.report.text())

        box = layout.box()
        box.label(text="Results", icon="NODE_COMPOSITING")
        row = box.row(align=True)
        row.operator("dibrgs.results", icon="RENDER_STILL")
        row.operator("dibrgs.render_active_camera", icon="CAMERA_DATA")
        r = box.row(align=True)
        sub = r.row(align=True)
        sub.enabled = not locked
        sub.prop(props, "fly_frames")
        r.operator("dibrgs.flythrough", icon="RENDER_ANIMATION")
        if not locked:
            _reason(box, context, "results", shown)
            _reason(box, context, "render_active_camera", shown)
        if props.results:
            box.prop(props, "result_view")
        for m in props.metrics:
            box.label(text=f"{m.name}: {m.value:.4g}")

        if props.error:
            col = layout.column()
            col.alert = True
            for line in props.error.splitlines()[:6]:
                col.label(text=line, icon="ERROR")
        elif props.message:
            layout.label(text=props.message, icon="INFO")


CLASSES = (DIBRGS_PT_main,)
