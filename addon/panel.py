"""The "Train DIBR-GS" panel in the 3D viewport sidebar (N panel, tab "DIBR-GS")."""
from __future__ import annotations

import bpy

from .operators import active_job


class DIBRGS_PT_main(bpy.types.Panel):
    bl_label = "Train DIBR-GS"
    bl_idname = "DIBRGS_PT_main"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "DIBR-GS"

    def draw(self, context):
        layout = self.layout
        props = context.scene.dibrgs
        busy = active_job() is not None

        box = layout.box()
        box.label(text="Scene", icon="OUTLINER_OB_CAMERA")
        box.prop(props, "scene_dir")
        row = box.row()
        row.enabled = not busy
        op = row.operator("dibrgs.import_scene", icon="IMPORT")
        op.directory = props.scene_dir
        box.prop(props, "work_dir")

        box = layout.box()
        box.label(text="Initialise", icon="POINTCLOUD_DATA")
        row = box.row()
        row.enabled = not busy
        row.operator("dibrgs.initialise", icon="PLAY")
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
        box.prop(props, "pseudo_count")
        box.operator("dibrgs.reset_path", icon="FILE_REFRESH")

        box = layout.box()
        box.label(text="Train", icon="SHADERFX")
        col = box.column()
        col.enabled = not busy
        col.prop(props, "preset")
        col.prop(props, "method")
        col.prop(props, "iterations")
        col.prop(props, "resume")
        if busy or props.job_running:
            box.progress(factor=props.job_fraction, type="BAR", text=f"{props.job_label}: {props.job_text}")
            box.operator("dibrgs.cancel", icon="CANCEL")
        else:
            box.operator("dibrgs.train", icon="PLAY")

        box = layout.box()
        box.label(text="Results", icon="NODE_COMPOSITING")
        row = box.row(align=True)
        row.enabled = not busy
        row.operator("dibrgs.results", icon="RENDER_STILL")
        row.operator("dibrgs.render_active_camera", icon="CAMERA_DATA")
        r = box.row(align=True)
        r.enabled = not busy
        r.prop(props, "fly_frames")
        r.operator("dibrgs.flythrough", icon="RENDER_ANIMATION")
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
