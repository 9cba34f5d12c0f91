"""Operators of the "Train DIBR-GS" panel.

Scene import and path editing run in Blender's own Python (numpy only, see
``dibrgs_core.bridge.describe``). Each step that needs torch runs ``dibrgs``
in a subprocess of the training interpreter (``dibrgs_core.bridge.jobs``).
Interactively a job runs in the background: an application timer polls the
subprocess and the panel draws its progress from the runner. With
``blocking=True``, in background mode or without a window the job runs to its
end before the operator returns.

The running job lives in memory only, never in the file: a file saved during
a run reopens with no job, and opening another file stops the running job
(training keeps its checkpoint). A job captures everything it depends on
(folders, scene description, cameras) when it starts. Every operator has a
``poll()``; :func:`why_not` gives its reason, which the panel shows.
"""
from __future__ import annotations

import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import bpy
from bpy.app.handlers import persistent
from bpy.props import BoolProperty, StringProperty

from . import results, scene_build, setup
from ._core import describe, errors, jobs, path as path_mod, pinhole
from .preferences import settings

TIMER_S = 0.25
_SETUP_SIGNS = ("No module named", "ModuleNotFoundError", "ImportError", "cannot start")


class UserError(Exception):
    """A problem the user can fix; reported as an error, nothing is changed."""


class SetupError(UserError):
    """No usable training Python (a successful Set up / Check clears it from the panel)."""


@dataclass
class Job:
    label: str
    runner: "jobs.JobRunner"
    #: Loads the results into Blender once every step succeeded; returns the message.
    finish: Callable[[bpy.types.Context], str]
    scene_name: str = ""
    blocking: bool = False
    #: Another file was opened while it ran: it was told to stop and loads nothing.
    detached: bool = False


#: The job running now (one at a time).
_active: Job | None = None
#: Jobs told to stop because another file was opened; polled until their process has ended.
_detached: list[Job] = []


def running_job() -> Job | None:
    """The job running now, or None. Also the liveness check: a job nobody polls gets its timer back."""
    job = _active
    if job is None or job.detached or job.runner.finished:
        return None
    if not job.blocking and not bpy.app.timers.is_registered(_tick):
        bpy.app.timers.register(_tick, first_interval=0.0, persistent=True)
    return job


def job_progress(job: Job) -> tuple[float, str]:
    """(fraction, one line) of a job's current step, for the progress bar."""
    r = job.runner
    step = r.step
    if step is None:
        return 0.0, f"{job.label}: starting"
    if step.progress:
        return r.progress.fraction, f"{step.label}: {r.progress.text()}"
    return r.index / len(r.steps), f"{step.label} ({r.index + 1}/{len(r.steps)})"


def cancel_running(grace_s: float = 30.0) -> Job | None:
    """Ask the running job to stop (SIGINT: training writes its checkpoint); None if nothing runs."""
    job = running_job()
    if job is not None:
        job.runner.cancel(grace_s=grace_s)
    return job


def stop_all(grace_s: float = 5.0) -> None:
    """Stop every job and wait for its process (the add-on is being disabled)."""
    global _active
    cancel_running(grace_s=grace_s)
    for job in ([_active] if _active is not None else []) + _detached:
        job.runner.wait(interval_s=0.1)
    _active = None
    _detached.clear()
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)


def _set_error(props, text: str, setup_problem: bool = False) -> None:
    props.error, props.error_is_setup = text, setup_problem


# ---------------------------------------------------------------------------
# what each operator needs (poll reasons, also shown in the panel)
# ---------------------------------------------------------------------------
def has_scene() -> bool:
    return scene_build.SCENE_TEXT in bpy.data.texts


def _work(props) -> Path:
    return Path(bpy.path.abspath(props.work_dir)).resolve()


def why_not(context: bpy.types.Context, action: str) -> str | None:
    """Why ``action`` (an operator name without ``dibrgs.``) cannot run now, or None."""
    scene = getattr(context, "scene", None)
    if scene is None or not hasattr(scene, "dibrgs"):
        return "no scene"
    props = scene.dibrgs
    job = running_job()
    if action == "cancel":
        return None if job is not None else "nothing is running"
    if job is not None:
        return f"{job.label} is running: wait for it or cancel it"
    if action == "import_scene":
        return None
    if not has_scene():
        return "import a scene first"
    if action == "reset_path":
        return None
    if not props.work_dir:
        return "set a run folder first"
    problem = setup.python_problem(context)
    if problem:
        return problem
    if action == "initialise":
        return None
    if action == "train":
        return None if props.path_curve is not None else "no pseudo-view path: Reset Path"
    problem = jobs.model_problem(_work(props))
    if problem:
        return problem
    if action == "render_active_camera" and _render_camera(context) is None:
        return "no camera: make a camera active or set the scene camera"
    if action in ("results", "flythrough") and props.path_curve is None:
        return "no pseudo-view path: Reset Path"
    return None


def _poll(cls, context, action: str) -> bool:
    reason = why_not(context, action)
    if reason:
        cls.poll_message_set(reason)
    return reason is None


def _render_camera(context) -> bpy.types.Object | None:
    obj = context.active_object
    if obj is not None and obj.type == "CAMERA":
        return obj
    return context.scene.camera


# ---------------------------------------------------------------------------
# import and path
# ---------------------------------------------------------------------------
class DIBRGS_OT_import_scene(bpy.types.Operator):
    """Import a scene (LEVIR-NVS, COLMAP, transforms.json, Metashape, OpenDroneMap, Meshroom, OpenMVG, Bundler, RealityCapture): one camera per view, the path, the render size"""

    bl_idname = "dibrgs.import_scene"
    bl_label = "Import Scene"
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(subtype="DIR_PATH", options={"SKIP_SAVE"})

    @classmethod
    def poll(cls, context):
        return _poll(cls, context, "import_scene")

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        props = context.scene.dibrgs
        root = Path(bpy.path.abspath(self.directory or props.scene_dir or "")).resolve()
        try:
            desc = read_description(root)
        except UserError as e:
            _set_error(props, str(e))
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        objs = scene_build.build_scene(context, desc)
        plan = scene_build.plan_path(desc)
        scene_build.create_path(context, plan)
        props.scene_dir = str(root)
        props.reference_view = desc["train"][0] if desc["train"] else desc["views"][0]["name"]
        props.preset = settings(context).default_preset
        if not props.work_dir:
            props.work_dir = str(Path(tempfile.gettempdir()) / "dibrgs" / root.name)
        props.decisions.clear()
        n = {s: sum(v["split"] == s for v in desc["views"]) for s in ("train", "test", "other")}
        props.message = (f"Imported {len(objs)} views from {root.name} ({desc['layout_name']}): "
                         f"{n['train']} training, {n['test']} held-out, {n['other']} other; "
                         f"pseudo-view path: {plan.kind}")
        left_out = jobs.pseudo_views_left_out(props.preset, n["train"])
        if left_out:  # the path still shows the trajectory; an edited one would not be used either
            props.message += f" (training leaves pseudo views out: {left_out})"
        turned = sum(v.get("orientation", 1) != 1 for v in desc["views"])
        undistorted = sum(bool(v.get("undistorted")) for v in desc["views"])
        if undistorted:  # the background shows the photo as taken, a few pixels off at the edges
            props.message += f"; {undistorted} cameras undistorted as training reads them"
        if turned:
            props.message += f"; {turned} photos turned upright by their EXIF orientation"
        _set_error(props, "")
        self.report({"INFO"}, props.message)
        return {"FINISHED"}


def read_description(root: Path) -> dict[str, Any]:
    """The scene description of ``root``, read in this Python; UserError with the reader's message."""
    if not root.is_dir():
        raise UserError(f"{root}: not a folder")
    try:
        desc = describe.describe_scene(root)
    except errors.InputError as e:
        raise UserError(f"Cannot import {root}: {e.problem if e.path == root else e}") from None
    if not desc["views"]:
        raise UserError(f"Cannot import {root}: no views")
    return desc


class DIBRGS_OT_reset_path(bpy.types.Operator):
    """Replace the pseudo-view path by one along the training cameras' trajectory: a circle round an orbit, else lines along the flight strips and between neighbouring cameras"""

    bl_idname = "dibrgs.reset_path"
    bl_label = "Reset Path"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return _poll(cls, context, "reset_path")

    def execute(self, context):
        plan = scene_build.plan_path(scene_build.scene_description())
        scene_build.create_path(context, plan)
        self.report({"INFO"}, f"Pseudo-view path: {plan.kind} ({plan.reason})")
        return {"FINISHED"}


# ---------------------------------------------------------------------------
# subprocess jobs
# ---------------------------------------------------------------------------
@dataclass
class Run:
    """What a job depends on, captured when it starts (later edits of the panel change nothing)."""

    python: str
    work: Path
    scene: Path
    desc: dict[str, Any]

    @property
    def blender(self) -> Path:
        return self.work / "blender"

    @property
    def split(self) -> tuple[list[str], list[str]] | None:
        """(training, held-out) views when the user moved view cameras, else None (the scene's own split)."""
        if self.desc.get("split_source") != scene_build.SPLIT_MOVED:
            return None
        return list(self.desc["train"]), list(self.desc["test"])

    def write_cameras(self, name: str, cams: list["pinhole.Camera"]) -> Path:
        """``cams`` (Blender's, relative to the description's origin) as ``blender/NAME`` for the
        command line, in the scene files' frame."""
        return path_mod.write_camera_list(self.blender / name, cams, self.desc.get("origin"))

    def step(self, label: str, cmd: list[str], progress: bool = False) -> "jobs.Step":
        log = self.blender / "logs" / f"{label.lower().replace(' ', '_').replace('-', '_')}.log"
        return jobs.Step(label=label, cmd=cmd, log_path=log, progress=progress)


def _run(context) -> Run:
    props = context.scene.dibrgs
    python, why = setup.chosen_python(context)
    if python is None:
        raise SetupError(why)
    if not props.work_dir:
        raise UserError("set a run folder first")
    try:
        desc = scene_build.scene_description()
    except ValueError as e:
        raise UserError(str(e)) from None
    if not desc["train"]:
        raise UserError(f"no view camera in the '{scene_build.TRAIN_COLLECTION}' collection: move the cameras "
                        "to train on there")
    return Run(python=python, work=_work(props), scene=Path(desc["root"]), desc=desc)


class _JobOperator:
    """Runs the :class:`Job` from :meth:`build`, in the background or blocking."""

    action = ""
    blocking: BoolProperty(name="Blocking", default=False, options={"SKIP_SAVE"},
                           description="Wait for the subprocess instead of running it in the background")

    @classmethod
    def poll(cls, context):
        return _poll(cls, context, cls.action)

    def build(self, context) -> Job:
        raise NotImplementedError

    def execute(self, context):
        global _active
        props = context.scene.dibrgs
        try:
            job = self.build(context)
        except (UserError, ValueError, OSError) as e:  # OSError: the run folder cannot be written
            _set_error(props, str(e), setup_problem=isinstance(e, SetupError))
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        job.scene_name = context.scene.name
        job.blocking = bool(self.blocking or bpy.app.background or context.window is None)
        _set_error(props, "")
        props.message = ""
        try:
            job.runner.start()
        except OSError as e:  # e.g. the run folder cannot be written
            _set_error(props, f"{job.label}: cannot start ({e})")
            self.report({"ERROR"}, props.error)
            return {"CANCELLED"}
        _active = job
        if not job.blocking:
            if not bpy.app.timers.is_registered(_tick):
                bpy.app.timers.register(_tick, first_interval=TIMER_S, persistent=True)
            return {"FINISHED"}
        last = ""
        while not job.runner.finished:
            job.runner.poll()
            text = job_progress(job)[1]
            if text != last:
                last = text
                print(f"[DIBR-GS] {text}", flush=True)
            time.sleep(0.1)
        level, text = _end(context, job)
        self.report({level}, text)
        return {"FINISHED"} if level == "INFO" else {"CANCELLED"}


def _end(context, job: Job) -> tuple[str, str]:
    """Load the results of a finished job into ``context.scene``; (report level, message)."""
    global _active
    if _active is job:
        _active = None
    props = context.scene.dibrgs
    state = job.runner.state
    if state == "done":
        try:
            props.message = job.finish(context)
        except (UserError, ValueError, RuntimeError, OSError) as e:
            _set_error(props, f"{job.label} finished but its results could not be loaded: {e}")
            return "ERROR", props.error
        return "INFO", props.message
    if state == "cancelled":
        props.message = f"{job.label} cancelled" + (
            "; its last checkpoint is kept in the run folder (train with Resume to continue)"
            if job.label == "Training" else "")
        return "WARNING", props.message
    err = job.runner.error or f"{job.label} failed"
    _set_error(props, err, setup_problem=any(s in err for s in _SETUP_SIGNS))
    return "ERROR", err


def _redraw() -> None:
    wm = bpy.context.window_manager
    for win in wm.windows if wm else []:
        for area in win.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


def _tick() -> float | None:
    """Polls the background job; loads its results into its scene when it ends."""
    global _active
    for old in list(_detached):
        old.runner.poll()
        if old.runner.finished:
            _detached.remove(old)
    job = _active
    if job is None:
        return TIMER_S if _detached else None
    try:
        job.runner.poll()
    except Exception as e:  # never leave a job that nobody polls
        job.runner.cancel(grace_s=5.0)
        print(f"[DIBR-GS] polling {job.label} failed: {e}", flush=True)
    _redraw()
    if not job.runner.finished:
        return TIMER_S
    scene = bpy.data.scenes.get(job.scene_name)
    if scene is None:  # its scene was deleted: nothing to load into
        _active = None
        return TIMER_S if _detached else None
    wm = bpy.context.window_manager
    override = {"scene": scene}
    if wm is not None and wm.windows:
        override["window"] = wm.windows[0]
    with bpy.context.temp_override(**override):
        level, text = _end(bpy.context, job)
    print(f"[DIBR-GS] {text}", flush=True)
    return TIMER_S if _detached else None


@persistent
def _load_pre(*_args) -> None:
    global _active
    job = running_job()
    if job is not None:  # its results belong to the file being closed
        job.runner.cancel()
        job.detached = True
        _active = None
        _detached.append(job)
        if not job.blocking and not bpy.app.timers.is_registered(_tick):
            bpy.app.timers.register(_tick, first_interval=TIMER_S, persistent=True)
        print(f"[DIBR-GS] {job.label} stopped: another file is being opened"
              + (" (training keeps its last checkpoint)" if job.label == "Training" else ""), flush=True)


#: Job state that earlier versions of the add-on saved in the file.
_LEGACY_KEYS = ("job_running", "job_label", "job_fraction", "job_text")


@persistent
def _load_post(*_args) -> None:
    """A loaded file never brings a job with it: drop job state older versions saved."""
    for scene in bpy.data.scenes:
        props = getattr(scene, "dibrgs", None)
        if props is None:
            continue
        for key in _LEGACY_KEYS:
            if key in props:
                del props[key]


HANDLERS = ((bpy.app.handlers.load_pre, _load_pre), (bpy.app.handlers.load_post, _load_post))


def _result_steps(context, run: Run) -> tuple[list["jobs.Step"], Callable[[bpy.types.Context], str]]:
    """Render held-out views and the pseudo path, evaluate; and the function that loads them."""
    props = context.scene.dibrgs
    held = scene_build.described_cameras(run.desc, "test")
    pseudo = scene_build.path_cameras(context, jobs.result_path_views(props.preset, props.pseudo_count), "pseudo")
    heldout_dir, pseudo_dir = run.blender / "renders" / "heldout", run.blender / "renders" / "pseudo"
    steps = []
    if held:
        cams = run.write_cameras("heldout_cameras.json", held)
        steps.append(run.step("Render held-out", jobs.render_command(run.python, run.work, cams, heldout_dir)))
    cams = run.write_cameras("pseudo_render_cameras.json", pseudo)
    steps.append(run.step("Render pseudo path", jobs.render_command(run.python, run.work, cams, pseudo_dir)))
    if held:
        steps.append(run.step("Evaluate", jobs.eval_command(run.python, run.work, settings(context).weights)))
    held_names, pseudo_names = [c.name for c in held], [c.name for c in pseudo]

    def finish(ctx) -> str:
        names = results.load_renders(ctx.scene, heldout_dir, held_names, "heldout")
        names += results.load_renders(ctx.scene, pseudo_dir, pseudo_names, "pseudo")
        results.show_all(ctx.scene, names[0] if names else None)
        msg = f"{len(names)} result images in the compositor"
        metrics = results.load_metrics(ctx.scene, run.work / "metrics.json")
        if metrics:
            msg += "; " + ", ".join(f"{k} {v:.4g}" for k, v in list(metrics.items())[:3])
        return msg

    return steps, finish


class DIBRGS_OT_initialise(_JobOperator, bpy.types.Operator):
    """Run the geometry stage (dibrgs init): dense points, height map and the stage decisions"""

    bl_idname = "dibrgs.initialise"
    bl_label = "Initialise"
    action = "initialise"

    def build(self, context) -> Job:
        run = _run(context)
        step = run.step("Initialise", jobs.init_command(run.python, run.scene, run.work, settings(context).weights,
                                                        run.split))

        def finish(ctx) -> str:
            n = results.load_init(ctx, run.work / "init")
            return f"Initialised: {n} dense points" + (", height map" if scene_build.HEIGHT_NAME in bpy.data.objects
                                                       else "")

        return Job("Initialise", jobs.JobRunner([step]), finish)


class DIBRGS_OT_train(_JobOperator, bpy.types.Operator):
    """Train on the imported scene in a subprocess, then render held-out views and the path into the compositor"""

    bl_idname = "dibrgs.train"
    bl_label = "Train"
    action = "train"

    def build(self, context) -> Job:
        props = context.scene.dibrgs
        run = _run(context)
        # An edited path is the user's: training takes its cameras as they are. An unedited one
        # only shows the trajectory, which training samples itself, as the command line does.
        pseudo_json = None
        if scene_build.training_takes_path(context, run.work, props.resume):
            pseudo = scene_build.path_cameras(context, jobs.pseudo_view_count(props.preset, props.pseudo_count),
                                              "pseudo")
            pseudo_json = run.write_cameras("pseudo_path.json", pseudo)
        opts = jobs.TrainOptions(preset=props.preset, method=props.method, iterations=props.iterations or None,
                                 resolution_scale=props.resolution_scale or None,
                                 pseudo_views=props.pseudo_count or None, pseudo_path=pseudo_json,
                                 resume=props.resume, weights=settings(context).weights, split=run.split)
        steps = [run.step("Training", jobs.train_command(run.python, run.scene, run.work, opts), progress=True)]
        more, finish_results = _result_steps(context, run)

        def finish(ctx) -> str:
            results.load_decisions(ctx.scene, run.work / "report.json")
            return "Trained; " + finish_results(ctx)

        return Job("Training", jobs.JobRunner(steps + more), finish)


class DIBRGS_OT_results(_JobOperator, bpy.types.Operator):
    """Render the held-out views and the pseudo path with the trained model into the compositor"""

    bl_idname = "dibrgs.results"
    bl_label = "Render Results"
    action = "results"

    def build(self, context) -> Job:
        run = _run(context)
        problem = jobs.model_problem(run.work)
        if problem:
            raise UserError(problem)
        steps, finish = _result_steps(context, run)
        return Job("Results", jobs.JobRunner(steps), finish)


class DIBRGS_OT_flythrough(_JobOperator, bpy.types.Operator):
    """Render the trained model along the path as an image sequence with an animated camera"""

    bl_idname = "dibrgs.flythrough"
    bl_label = "Fly-through"
    action = "flythrough"

    def build(self, context) -> Job:
        props = context.scene.dibrgs
        run = _run(context)
        problem = jobs.model_problem(run.work)
        if problem:
            raise UserError(problem)
        cams = scene_build.path_cameras(context, props.fly_frames, "fly", route=True)
        for k, c in enumerate(cams):  # frame numbers in the names: Blender reads them as a sequence
            c.name = f"fly_{k + 1:04d}"
        out = run.blender / "renders" / "flythrough"
        cams_json = run.write_cameras("flythrough_cameras.json", cams)
        step = run.step("Fly-through", jobs.render_command(run.python, run.work, cams_json, out))

        def finish(ctx) -> str:
            results.flythrough(ctx, out, cams)
            return f"Fly-through: {len(cams)} frames in {out}"

        return Job("Fly-through", jobs.JobRunner([step]), finish)


class DIBRGS_OT_render_active_camera(_JobOperator, bpy.types.Operator):
    """Render the trained model from the scene camera (any camera you place) into the compositor"""

    bl_idname = "dibrgs.render_active_camera"
    bl_label = "Render Active Camera"
    action = "render_active_camera"

    def build(self, context) -> Job:
        run = _run(context)
        obj = _render_camera(context)
        if obj is None:
            raise UserError("no camera: make a camera active or set the scene camera")
        problem = jobs.model_problem(run.work)
        if problem:
            raise UserError(problem)
        cam = scene_build.camera_from_object(obj, context.scene)
        cam.name = "active_" + bpy.path.clean_name(obj.name)
        out = run.blender / "renders" / "active"
        cams_json = run.write_cameras("active_camera.json", [cam])
        step = run.step("Render camera", jobs.render_command(run.python, run.work, cams_json, out))
        obj_name = obj.name

        def finish(ctx) -> str:
            names = results.load_renders(ctx.scene, out, [cam.name], "active")
            results.show_all(ctx.scene, names[0])
            return f"Rendered {obj_name} into the compositor"

        return Job("Render camera", jobs.JobRunner([step]), finish)


class DIBRGS_OT_cancel(bpy.types.Operator):
    """Stop the running job (training keeps its last checkpoint)"""

    bl_idname = "dibrgs.cancel"
    bl_label = "Cancel"

    @classmethod
    def poll(cls, context):
        return _poll(cls, context, "cancel")

    def execute(self, context):
        job = cancel_running()
        self.report({"INFO"}, f"stopping {job.label}...")
        return {"FINISHED"}


CLASSES = (DIBRGS_OT_import_scene, DIBRGS_OT_reset_path, DIBRGS_OT_initialise, DIBRGS_OT_train,
           DIBRGS_OT_results, DIBRGS_OT_flythrough, DIBRGS_OT_render_active_camera, DIBRGS_OT_cancel)
