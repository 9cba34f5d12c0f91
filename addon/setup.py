"""The training interpreter: which one, and "Set up / Check" in the background.

Scene import and everything that needs no torch runs in Blender's own Python;
training, rendering and evaluation run as ``PYTHON -m dibrgs_core ...`` with
the interpreter chosen here. Choosing it never starts a process: the
preference, else ``$DIBRGS_PYTHON``, else Blender's own Python when torch is
installed there. "Set up / Check" runs ``dibrgs check --json`` in that
interpreter without blocking Blender (imports every dependency, builds the C++
rasterizer once) and the preferences show each item, OK or what fixes it.
"""
from __future__ import annotations

import importlib.util
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import bpy
from bpy.props import BoolProperty, StringProperty

from ._core import checks, jobs

TIMER_S = 0.25
PREFS_HINT = "Edit > Preferences > Add-ons > DIBR-GS"


@dataclass
class CheckRun:
    python: str
    runner: "jobs.JobRunner"
    report: "checks.CheckReport"
    log_path: Path

    @property
    def running(self) -> bool:
        return not self.runner.finished

    def failure(self) -> str | None:
        """Why the interpreter is not usable (None when the check passed or still runs)."""
        if self.running or self.report.ok:
            return None
        if self.report.ok is False:
            return (f"the training Python lacks {', '.join(self.report.problems())}: fix it and press "
                    f"Set up / Check again ({PREFS_HINT})")
        return (f"the check of {self.python} stopped ({self.runner.error or 'no result'}); "
                f"log: {self.log_path}").splitlines()[0]


#: The latest check per interpreter path (this Blender session only).
_runs: dict[str, CheckRun] = {}


def chosen_python(context: bpy.types.Context | None = None) -> tuple[str | None, str]:
    """(interpreter, "") or (None, why there is none); never starts a process."""
    from .preferences import settings

    chosen = os.path.expanduser(settings(context).python_path or os.environ.get("DIBRGS_PYTHON", ""))
    if chosen:
        if not Path(chosen).is_file():
            return None, f"training Python {chosen} not found: set it in {PREFS_HINT}"
        return chosen, ""
    if importlib.util.find_spec("torch") is not None:
        return sys.executable, ""
    return None, f"set the training Python in {PREFS_HINT} (README, section Blender)"


def latest(python: str | None) -> CheckRun | None:
    return _runs.get(python) if python else None


def python_problem(context: bpy.types.Context | None = None) -> str | None:
    """Why training cannot start with the chosen interpreter now, or None."""
    python, why = chosen_python(context)
    if python is None:
        return why
    run = latest(python)
    if run is None:
        return None  # never checked: training itself reports what is missing
    if run.running:
        return "Set up / Check is running: wait for it to finish"
    return run.failure()


def start_check(python: str) -> CheckRun:
    """Start ``dibrgs check`` in the background (the timer polls it)."""
    log = Path(tempfile.gettempdir()) / "dibrgs" / f"check-{os.getpid()}.log"
    if log.exists():
        log.unlink()
    report = checks.CheckReport()
    runner = jobs.JobRunner([jobs.Step("Set up / Check", jobs.check_command(python), log)],
                            on_line=report.feed)
    run = _runs[python] = CheckRun(python, runner, report, log)
    runner.start()
    if not bpy.app.timers.is_registered(_tick):
        bpy.app.timers.register(_tick, first_interval=TIMER_S, persistent=True)
    return run


def _finished(run: CheckRun) -> None:
    if run.report.ok:  # errors that came from a broken set-up are stale now
        for scene in bpy.data.scenes:
            props = getattr(scene, "dibrgs", None)
            if props is not None and props.error_is_setup:
                props.error, props.error_is_setup = "", False


def _redraw() -> None:
    wm = bpy.context.window_manager
    for win in wm.windows if wm else []:
        for area in win.screen.areas:
            if area.type in ("PREFERENCES", "VIEW_3D"):
                area.tag_redraw()


def _tick() -> float | None:
    busy = False
    for run in list(_runs.values()):
        if run.running:
            run.runner.poll()
            if run.running:
                busy = True
            else:
                _finished(run)
    _redraw()
    return TIMER_S if busy else None


def wait(run: CheckRun, interval_s: float = 0.1) -> None:
    """Block until the check ends (background mode, tests)."""
    run.runner.wait(interval_s=interval_s)
    _finished(run)


def stop_all() -> None:
    for run in _runs.values():
        if run.running:
            run.runner.cancel(grace_s=2.0)
    if bpy.app.timers.is_registered(_tick):
        bpy.app.timers.unregister(_tick)


class DIBRGS_OT_setup_check(bpy.types.Operator):
    """Check the training Python in the background: import every dependency, build the C++
    rasterizer (about 2 minutes the first time), report what is missing and how to fix it"""

    bl_idname = "dibrgs.setup_check"
    bl_label = "Set up / Check"

    blocking: BoolProperty(default=False, options={"SKIP_SAVE"},
                           description="Wait for the check instead of running it in the background")

    @classmethod
    def poll(cls, context):
        python, why = chosen_python(context)
        run = latest(python)
        if python is None:
            cls.poll_message_set(why)
            return False
        if run is not None and run.running:
            cls.poll_message_set("the check is running")
            return False
        return True

    def execute(self, context):
        python, _ = chosen_python(context)
        run = start_check(python)
        if self.blocking or bpy.app.background:
            wait(run)
            level = {"INFO"} if run.report.ok else {"ERROR"}
            self.report(level, run.report.text() if run.report.result else (run.failure() or "check failed"))
            return {"FINISHED"} if run.report.ok else {"CANCELLED"}
        return {"FINISHED"}


class DIBRGS_OT_copy_text(bpy.types.Operator):
    """Copy this command to the clipboard"""

    bl_idname = "dibrgs.copy_text"
    bl_label = "Copy"

    text: StringProperty(options={"SKIP_SAVE"})

    def execute(self, context):
        context.window_manager.clipboard = self.text
        self.report({"INFO"}, "copied: " + self.text)
        return {"FINISHED"}


def draw_check(layout: bpy.types.UILayout, context: bpy.types.Context) -> None:
    """The check's progress or its items, under the interpreter field of the preferences."""
    python, why = chosen_python(context)
    col = layout.column()
    col.operator(DIBRGS_OT_setup_check.bl_idname, icon="CHECKMARK")
    if python is None:
        col.label(text=why, icon="ERROR")
        return
    run = latest(python)
    if run is None:
        col.label(text=f"{python}: not checked yet in this session", icon="INFO")
        return
    if run.running:
        col.progress(factor=run.report.fraction, type="BAR", text=run.report.text())
    box = col.box()
    for item in run.report.items:
        icon = "CHECKMARK" if item.ok else ("ERROR" if item.required else "INFO")
        box.label(text=f"{item.name}: {item.detail}" + (f"  ({item.note})" if item.note else ""), icon=icon)
        if item.fix and not item.ok:
            row = box.row()
            row.label(text=item.fix)
            row.operator(DIBRGS_OT_copy_text.bl_idname, text="", icon="COPYDOWN").text = item.fix
    if run.running:
        return
    if run.report.ok:
        col.label(text="Ready to train", icon="CHECKMARK")
    else:
        col.alert = True
        col.label(text=run.failure() or "not ready", icon="ERROR")
        fix = (run.report.result or {}).get("fix")
        if fix:
            row = col.row()
            row.label(text=fix)
            row.operator(DIBRGS_OT_copy_text.bl_idname, text="", icon="COPYDOWN").text = fix


CLASSES = (DIBRGS_OT_setup_check, DIBRGS_OT_copy_text)
