"""Operators of the "Train DIBR-GS" panel.

Every heavy step runs ``dibrgs`` in a subprocess (``dibrgs_core.bridge.jobs``).
Interactively a job operator is modal: a window timer polls the subprocess
so Blender stays responsive and the panel shows progress. With
``blocking=True``, in background mode or without a window (batch mode,
tests) the same job runs to its end before the operator returns.
"""
from __future__ import annotations

import json
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import bpy
from bpy.props import BoolProperty, StringProperty

from . import results, scene_build
from ._core import jobs, path as path_mod
from .preferences import resolve_python, settings

TIMER_S = 0.25


class UserError(Exception):
    """A problem the user can fix; reported as an error, nothing is changed."""


@dataclass
class Job:
    label: str
    runner: "jobs.JobRunner"
    finish: Callable[[bpy.types.Context], str]


#: The job running now (one at a time), for the Cancel operator.
_active: Job | None = None


def active_job() -> Job | None:
    return _active


def _python(context) -> str:
    python, msg = resolve_python(context)
    if python is None:
        raise UserError(msg)
    return python


def work_dir(context) -> Path:
    props = context.scene.dibrgs
    if not props.work_dir:
        raise UserError("set a run folder first")
    return Path(bpy.path.abspath(props.work_dir)).resolve()


def scene_dir(context) -> Path:
    try:
        return Path(scene_build.scene_description()["root"])
    except ValueError as e:
        raise UserError(str(e)) from None


def blender_dir(context) -> Path:
    return work_dir(context) / "blender"


def _log(context, name: str) -> Path:
    return blender_dir(context) / "logs" / f"{name}.log"


# ---------------------------------------------------------------------------
# import and path
# ---------------------------------------------------------------------------
class DIBRGS_OT_import_scene(bpy.types.Operator):
    """Import a LEVIR-NVS or COLMAP scene: one camera per view, the path, the render size"""

    bl_idname = "dibrgs.import_scene"
    bl_label = "Import Scene"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(subtype="DIR_PATH", options={"SKIP_SAVE"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        props = context.scene.dibrgs
        root = Path(bpy.path.abspath(self.directory or props.scene_dir or "")).resolve()
        try:
            if not root.is_dir():
                raise UserError(f"{root}: not a folder")
            desc = describe(_python(context), root)
        except UserError as e:
            props.error = str(e)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        objs = scene_build.build_scene(context, desc)
        scene_build.create_path(context, scene_build.fit_orbit(desc))
        props.scene_dir = str(root)
        props.reference_view = desc["train"][0] if desc["train"] else desc["views"][0]["name"]
        props.preset = settings(context).default_preset
        if not props.work_dir:
            props.work_dir = str(Path(tempfile.gettempdir()) / "dibrgs" / root.name)
        props.decisions.clear()
        n = {s: sum(v["split"] == s for v in desc["views"]) for s in ("train", "test", "other")}
        props.message = (f"Imported {len(objs)} views from {root.name}: {n['train']} training, "
                         f"{n['test']} held-out, {n['other']} other")
        props.error = ""
        self.report({"INFO"}, props.message)
        return {"FINISHED"}


def describe(python: str, root: Path) -> dict:
    """Run the scene description subprocess; UserError with its message when the folder is rejected."""
    with tempfile.TemporaryDirectory(prefix="dibrgs-describe-") as tmp:
        out = Path(tmp) / "scene.json"
        r = subprocess.run(jobs.describe_command(python, root, out), env=jobs.subprocess_env(),
                           capture_output=True, text=True)
        if r.returncode != 0 or not out.exists():
            lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
            raise UserError(f"Cannot import {root}: {lines[-1] if lines else f'exit code {r.returncode}'}")
        desc = json.loads(out.read_text())
    if not desc["views"]:
        raise UserError(f"Cannot import {root}: no views")
    return desc


class DIBRGS_OT_reset_path(bpy.types.Operator):
    """Replace the pseudo-view path by the orbit fitted to the acquisition cameras"""

    bl_idname = "dibrgs.reset_path"
    bl_label = "Reset Path to Orbit"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        try:
            desc = scene_build.scene_description()
        except ValueError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        scene_build.create_path(context, scene_build.fit_orbit(desc))
        return {"FINISHED"}


# ---------------------------------------------------------------------------
# subprocess jobs
# ---------------------------------------------------------------------------
class _JobOperator:
    """Runs the :class:`Job` from :meth:`build`, modal or blocking."""

    blocking: BoolProperty(name="Blocking", default=False, options={"SKIP_SAVE"},
                           description="Wait for the subprocess instead of running it in the background")

    def build(self, context) -> Job:
        raise NotImplementedError

    def execute(self, context):
        global _active
        props = context.scene.dibrgs
        if _active is not None and not _active.runner.finished:
            self.report({"ERROR"}, f"{_active.label} is still running")
            return {"CANCELLED"}
        try:
            job = self.build(context)
        except (UserError, ValueError) as e:
            props.error = str(e)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        _active = job
        props.error, props.message = "", ""
        props.job_running, props.job_label, props.job_fraction, props.job_text = True, job.label, 0.0, ""
        job.runner.start()
        if self.blocking or bpy.app.background or context.window is None:
            last = ""
            while not job.runner.finished:
                job.runner.poll()
                self._mirror(context, job)
                if props.job_text != last and job.runner.step is not None and job.runner.step.progress:
                    last = props.job_text
                    print(f"[DIBR-GS] {job.runner.step.label}: {last}", flush=True)
                time.sleep(0.1)
            return self._end(context, job)
        self._timer = context.window_manager.event_timer_add(TIMER_S, window=context.window)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        job = _active
        job.runner.poll()
        self._mirror(context, job)
        for area in context.screen.areas if context.screen else []:
            if area.type == "VIEW_3D":
                area.tag_redraw()
        if not job.runner.finished:
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        return self._end(context, job)

    @staticmethod
    def _mirror(context, job: Job) -> None:
        props = context.scene.dibrgs
        r = job.runner
        step = r.step
        if step is None:
            return
        props.log_path = str(step.log_path)
        if step.progress:
            props.job_fraction = r.progress.fraction
            props.job_text = r.progress.text()
        else:
            props.job_fraction = r.index / len(r.steps)
            props.job_text = f"{step.label} ({r.index + 1}/{len(r.steps)})"

    def _end(self, context, job: Job):
        global _active
        props = context.scene.dibrgs
        props.job_running = False
        _active = None
        state = job.runner.state
        if state == "done":
            try:
                props.message = job.finish(context)
            except (UserError, ValueError, RuntimeError, OSError) as e:
                props.error = f"{job.label} finished but its results could not be loaded: {e}"
                self.report({"ERROR"}, props.error)
                return {"CANCELLED"}
            props.job_fraction, props.job_text = 1.0, "done"
            self.report({"INFO"}, props.message)
            return {"FINISHED"}
        if state == "cancelled":
            props.message = f"{job.label} cancelled" + (
                f"; the last checkpoint is kept in {work_dir(context)} (train with Resume to continue)"
                if job.label == "Training" else "")
            self.report({"WARNING"}, props.message)
            return {"CANCELLED"}
        props.error = job.runner.error or f"{job.label} failed"
        self.report({"ERROR"}, props.error)
        return {"CANCELLED"}


def _step(context, label: str, cmd: list[str], progress: bool = False) -> "jobs.Step":
    return jobs.Step(label=label, cmd=cmd, log_path=_log(context, label.lower().replace(" ", "_")),
                     progress=progress)


def _result_steps(context, python: str) -> list["jobs.Step"]:
    """Render held-out views and the pseudo path, evaluate the metrics."""
    desc = scene_build.scene_description()
    bdir, work = blender_dir(context), work_dir(context)
    held = scene_build.described_cameras(desc, "test")
    steps = []
    if held:
        cams = path_mod.write_camera_list(bdir / "heldout_cameras.json", held)
        steps.append(_step(context, "Render held-out", jobs.render_command(python, work, cams, bdir / "renders" / "heldout")))
    props = context.scene.dibrgs
    pseudo = scene_build.path_cameras(context, jobs.pseudo_view_count(props.preset, props.pseudo_count), "pseudo")
    cams = path_mod.write_camera_list(bdir / "pseudo_render_cameras.json", pseudo)
    steps.append(_step(context, "Render pseudo path", jobs.render_command(python, work, cams, bdir / "renders" / "pseudo")))
    if held:
        steps.append(_step(context, "Evaluate", jobs.eval_command(python, work, settings(context).weights)))
    return steps


def _finish_results(context) -> str:
    bdir, work = blender_dir(context), work_dir(context)
    desc = scene_build.scene_description()
    held = [v["name"] for v in desc["views"] if v["split"] == "test"]
    names = results.load_renders(context.scene, bdir / "renders" / "heldout", held, "heldout")
    pseudo = sorted(p.stem for p in (bdir / "renders" / "pseudo").glob("pseudo_*.png")
                    if not p.stem.endswith("_depth"))
    names += results.load_renders(context.scene, bdir / "renders" / "pseudo", pseudo, "pseudo")
    results.show_all(context.scene, names[0] if names else None)
    msg = f"{len(names)} result images in the compositor"
    metrics = results.load_metrics(context.scene, work / "metrics.json")
    if metrics:
        msg += "; " + ", ".join(f"{k} {v:.4g}" for k, v in list(metrics.items())[:3])
    return msg


class DIBRGS_OT_initialise(_JobOperator, bpy.types.Operator):
    """Run the geometry stage (dibrgs init): dense points, height map and the stage decisions"""

    bl_idname = "dibrgs.initialise"
    bl_label = "Initialise"

    def build(self, context) -> Job:
        python, work, root = _python(context), work_dir(context), scene_dir(context)
        step = _step(context, "Initialise", jobs.init_command(python, root, work, settings(context).weights))
        runner = jobs.JobRunner([step])

        def finish(ctx) -> str:
            init = work / "init"
            n = results.load_init(ctx, init)
            return f"Initialised: {n} dense points" + (", height map" if scene_build.HEIGHT_NAME in bpy.data.objects else "")

        return Job("Initialise", runner, finish)


class DIBRGS_OT_train(_JobOperator, bpy.types.Operator):
    """Train on the imported scene in a subprocess, then render held-out views and the path into the compositor"""

    bl_idname = "dibrgs.train"
    bl_label = "Train"

    def build(self, context) -> Job:
        props = context.scene.dibrgs
        python, work, root = _python(context), work_dir(context), scene_dir(context)
        # The path as it is now is what training uses.
        pseudo = scene_build.path_cameras(context, jobs.pseudo_view_count(props.preset, props.pseudo_count),
                                          "pseudo")
        pseudo_json = path_mod.write_camera_list(blender_dir(context) / "pseudo_path.json", pseudo)
        opts = jobs.TrainOptions(preset=props.preset, method=props.method,
                                 iterations=props.iterations or None, pseudo_path=pseudo_json,
                                 resume=props.resume, weights=settings(context).weights)
        steps = [_step(context, "Training", jobs.train_command(python, root, work, opts), progress=True)]
        steps += _result_steps(context, python)

        def finish(ctx) -> str:
            results.load_decisions(ctx.scene, work / "report.json")
            return "Trained; " + _finish_results(ctx)

        return Job("Training", jobs.JobRunner(steps), finish)


class DIBRGS_OT_results(_JobOperator, bpy.types.Operator):
    """Render the held-out views and the pseudo path with the trained model into the compositor"""

    bl_idname = "dibrgs.results"
    bl_label = "Render Results"

    def build(self, context) -> Job:
        python = _python(context)
        if not (work_dir(context) / "checkpoint.pt").exists():
            raise UserError(f"no trained model in {work_dir(context)}: train first")
        return Job("Results", jobs.JobRunner(_result_steps(context, python)), _finish_results)


class DIBRGS_OT_flythrough(_JobOperator, bpy.types.Operator):
    """Render the trained model along the path as an image sequence with an animated camera"""

    bl_idname = "dibrgs.flythrough"
    bl_label = "Fly-through"

    def build(self, context) -> Job:
        props = context.scene.dibrgs
        python, work = _python(context), work_dir(context)
        if not (work / "checkpoint.pt").exists():
            raise UserError(f"no trained model in {work}: train first")
        cams = scene_build.path_cameras(context, props.fly_frames, "fly")
        for k, c in enumerate(cams):  # frame numbers in the names: Blender reads them as a sequence
            c.name = f"fly_{k + 1:04d}"
        out = blender_dir(context) / "renders" / "flythrough"
        cams_json = path_mod.write_camera_list(blender_dir(context) / "flythrough_cameras.json", cams)
        step = _step(context, "Fly-through", jobs.render_command(python, work, cams_json, out))

        def finish(ctx) -> str:
            results.flythrough(ctx, out, cams)
            return f"Fly-through: {len(cams)} frames in {out}"

        return Job("Fly-through", jobs.JobRunner([step]), finish)


class DIBRGS_OT_render_active_camera(_JobOperator, bpy.types.Operator):
    """Render the trained model from the scene camera (any camera you place) into the compositor"""

    bl_idname = "dibrgs.render_active_camera"
    bl_label = "Render Active Camera"

    def build(self, context) -> Job:
        python, work = _python(context), work_dir(context)
        obj = context.active_object if context.active_object and context.active_object.type == "CAMERA" \
            else context.scene.camera
        if obj is None:
            raise UserError("no camera: make a camera active or set the scene camera")
        if not (work / "checkpoint.pt").exists():
            raise UserError(f"no trained model in {work}: train first")
        cam = scene_build.camera_from_object(obj, context.scene)
        cam.name = "active_" + bpy.path.clean_name(obj.name)
        out = blender_dir(context) / "renders" / "active"
        cams_json = path_mod.write_camera_list(blender_dir(context) / "active_camera.json", [cam])
        step = _step(context, "Render camera", jobs.render_command(python, work, cams_json, out))

        def finish(ctx) -> str:
            names = results.load_renders(ctx.scene, out, [cam.name], "active")
            results.show_all(ctx.scene, names[0])
            return f"Rendered {obj.name} into the compositor"

        return Job("Render camera", jobs.JobRunner([step]), finish)


class DIBRGS_OT_cancel(bpy.types.Operator):
    """Stop the running job (training keeps its last checkpoint)"""

    bl_idname = "dibrgs.cancel"
    bl_label = "Cancel"

    def execute(self, context):
        job = _active
        if job is None or job.runner.finished:
            self.report({"WARNING"}, "nothing is running")
            return {"CANCELLED"}
        job.runner.cancel()
        context.scene.dibrgs.job_text = "cancelling..."
        return {"FINISHED"}


CLASSES = (DIBRGS_OT_import_scene, DIBRGS_OT_reset_path, DIBRGS_OT_initialise, DIBRGS_OT_train,
           DIBRGS_OT_results, DIBRGS_OT_flythrough, DIBRGS_OT_render_active_camera, DIBRGS_OT_cancel)
