"""Batch mode of the add-on: import, initialise, path, train, results; save a .blend.

From the installed extension (Blender 4.2+ command-line command, registered by the add-on)::

    blender -b -c dibrgs --scene DIR --out DIR [training options]

From a checkout (``scripts/run.py`` calls :func:`main`)::

    blender -b -P scripts/run.py -- --scene DIR --out DIR [training options]
    python scripts/run.py --scene DIR --out DIR [training options]     # with the bpy module

Everything runs through the add-on's own operators (blocking variant), so the
saved ``OUT/dibrgs.blend`` is what the panel would have produced. Training
uses ``--python`` (default: ``$DIBRGS_PYTHON``, else this Python when it has
torch). Exit codes: 0 success, 1 a step failed (message on stderr), 2 bad
arguments, 130 interrupted: SIGINT (Ctrl+C) or SIGTERM stops the running
step (training writes its checkpoint; ``--resume`` continues) and prints one
line; a second signal kills the step at once.
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path

import bpy

from . import operators, scene_build
from ._core import errors, jobs, split, train_config

CLI_COMMAND = "dibrgs"


def parse_args(argv: list[str], prog: str) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog=prog, description="DIBR-GS batch mode: import, initialise, path, train, results, save .blend.")
    p.add_argument("--scene", type=Path, required=True,
                   help="scene folder: LEVIR-NVS, COLMAP, transforms.json, Metashape XML, OpenDroneMap, "
                        "Meshroom, OpenMVG, Bundler or RealityCapture XMP")
    p.add_argument("--out", type=Path, required=True, help="run folder (checkpoint, renders, the .blend)")
    p.add_argument("--preset", choices=train_config.PRESETS, default="cpu")
    p.add_argument("--method", choices=jobs.METHODS, default="dibrgs")
    p.add_argument("--train", default=None, metavar="NAMES",
                   help="training views, as `dibrgs train --train` (comma-separated names or LEVIR ids, or 'all'); "
                        "overrides the scene's split.json")
    p.add_argument("--test", default=None, metavar="NAMES",
                   help="held-out views, as `dibrgs train --test` (or 'none')")
    p.add_argument("--iterations", type=int, default=0, help="0: the preset's")
    p.add_argument("--resolution-scale", type=float, default=0.0,
                   help=f"scale of the photos, in (0, {jobs.MAX_RESOLUTION_SCALE:g}] (0: the preset's; cpu: long side "
                        "at most 512 px)")
    p.add_argument("--pseudo-views", type=int, default=0,
                   help="pseudo views sampled along the path (0: the preset's number, 96 for cpu)")
    p.add_argument("--fly-frames", type=int, default=0, help="render a fly-through of this many frames (0: none)")
    p.add_argument("--no-init", action="store_true", help="skip the separate initialise step (training runs it)")
    p.add_argument("--resume", action="store_true", help="continue from the run folder's checkpoint")
    p.add_argument("--python", default=None, help="interpreter with torch and the DIBR-GS dependencies")
    p.add_argument("--blend", type=Path, default=None, help="output .blend (default OUT/dibrgs.blend)")
    args = p.parse_args(argv)
    if args.iterations < 0 or args.pseudo_views < 0 or args.fly_frames < 0:
        p.error("--iterations, --pseudo-views and --fly-frames must be >= 0")
    if not 0 <= args.resolution_scale <= jobs.MAX_RESOLUTION_SCALE:
        p.error(f"--resolution-scale must be in (0, {jobs.MAX_RESOLUTION_SCALE:g}], or 0 for the preset's")
    if not args.scene.is_dir():
        p.error(f"--scene {args.scene}: not a folder")
    return args


class _Interrupted:
    """SIGINT/SIGTERM handler: the first signal stops the running step cleanly, the second kills it."""

    def __init__(self) -> None:
        self.signal: str | None = None
        self.count = 0

    def __call__(self, signum, _frame) -> None:
        self.count += 1
        self.signal = self.signal or signal.Signals(signum).name
        operators.cancel_running(grace_s=60.0 if self.count == 1 else 0.0)


def main(argv: list[str], prog: str = f"blender -b -c {CLI_COMMAND}") -> int:
    """Run the batch; the add-on must be registered. Returns the exit code."""
    try:
        args = parse_args(argv, prog)
    except SystemExit as e:  # argparse printed the usage and the error
        return int(e.code or 0)
    if args.python:
        os.environ["DIBRGS_PYTHON"] = args.python
    interrupted = _Interrupted()
    old = {s: signal.signal(s, interrupted) for s in (signal.SIGINT, signal.SIGTERM)}
    out = args.out.resolve()
    try:
        _empty_file()
        props = bpy.context.scene.dibrgs
        props.work_dir = str(out)
        steps = [("import", lambda: bpy.ops.dibrgs.import_scene(directory=str(args.scene.resolve())))]
        if args.train is not None or args.test is not None:
            steps.append(("split", lambda: _choose_split(args.train, args.test)))
        if not args.no_init:
            steps.append(("initialise", lambda: bpy.ops.dibrgs.initialise(blocking=True)))
        steps.append(("train", lambda: bpy.ops.dibrgs.train(blocking=True)))
        if args.fly_frames:
            steps.append(("fly-through", lambda: bpy.ops.dibrgs.flythrough(blocking=True)))
        for name, op in steps:
            if name == "train":  # the import sets the preferences' preset; the command line wins
                props.preset, props.method = args.preset, args.method
                props.iterations, props.pseudo_count = args.iterations, args.pseudo_views
                props.resolution_scale = args.resolution_scale
                props.resume = args.resume
                props.fly_frames = max(args.fly_frames, 2)
            print(f"[DIBR-GS] {name} ...", flush=True)
            try:
                result = op()
            except RuntimeError as e:  # an operator's error report, or its poll() refused
                if interrupted.signal:
                    break
                print(f"{prog}: {name} failed: {str(e).strip().splitlines()[-1]}", file=sys.stderr)
                return 1
            if interrupted.signal:
                break
            if "FINISHED" not in result:
                print(f"{prog}: {name} failed: {props.error or result}", file=sys.stderr)
                return 2 if name == "split" else 1  # a --train / --test the scene does not have
            print(f"[DIBR-GS] {props.message}", flush=True)
        if interrupted.signal:
            kept = " (the checkpoint is kept: run again with --resume to continue)" if (
                out / jobs.CHECKPOINT_FILE).is_file() else ""
            print(f"{prog}: interrupted by {interrupted.signal} during {name}{kept}", file=sys.stderr, flush=True)
            return 130
        blend = (args.blend or out / "dibrgs.blend").resolve()
        blend.parent.mkdir(parents=True, exist_ok=True)
        bpy.ops.wm.save_as_mainfile(filepath=str(blend))
        print(f"[DIBR-GS] saved {blend}", flush=True)
        return 0
    finally:
        job = operators.cancel_running(grace_s=10.0)  # never leave a child behind
        if job is not None:
            job.runner.wait(interval_s=0.1)
        for s, h in old.items():
            signal.signal(s, h)


def _choose_split(train: str | None, test: str | None) -> set[str]:
    """Move the view cameras into the collections of the split ``--train`` / ``--test`` name (the
    rules of ``dibrgs train``'s options), as a user would in the panel."""
    desc = scene_build.scene_description(imported=True)
    names = [v["name"] for v in desc["views"]]
    try:
        tr, te, _ = split.make_split(Path(desc["root"]), names, _names(train), _names(test))
    except errors.InputError as e:
        bpy.context.scene.dibrgs.error = str(e)
        return {"CANCELLED"}
    scene_build.move_to_split(bpy.context, tr, te)
    bpy.context.scene.dibrgs.message = f"split: train {tr}, held out {te}"
    return {"FINISHED"}


def _names(s: str | None) -> list[str] | None:
    return None if s is None else [x.strip() for x in s.split(",") if x.strip()]


def _empty_file() -> None:
    """An empty file to build the scene in, keeping the registered add-ons."""
    bpy.ops.wm.read_homefile(use_empty=True)
    if not hasattr(bpy.types.Scene, "dibrgs"):
        raise RuntimeError("the DIBR-GS add-on is not registered")


def cli_command(argv: list[str]) -> int:
    """``blender -b -c dibrgs ...``: Blender's command-line entry of the installed extension."""
    if not bpy.app.background:
        print(f"{CLI_COMMAND}: run it in background mode: blender -b -c {CLI_COMMAND} ...", file=sys.stderr)
        return 2
    return main(list(argv))
