"""Batch mode of the DIBR-GS Blender add-on: import, initialise, path, train, results; save a .blend.

    blender -b -P scripts/run.py -- --scene DIR --out DIR [training options]
    python scripts/run.py --scene DIR --out DIR [training options]      # with the bpy module

Everything runs through the add-on's own operators (blocking variant), so the
saved ``OUT/dibrgs.blend`` is what the panel would have produced: cameras in
their collections, dense points, height map, the editable path, the
compositor with the renders, metrics and (with ``--fly-frames``) the
animated fly-through camera. Training runs with ``--python`` (default:
``$DIBRGS_PYTHON``, else this Python when it can import torch).
Exit codes: 0 success, 1 a step failed (message on stderr), 2 bad arguments.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def parse_args(argv: list[str]) -> argparse.Namespace:
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    from dibrgs_core.common.modes import MethodName, PresetName, choices

    p = argparse.ArgumentParser(
        prog="run.py", description="DIBR-GS batch mode: import, initialise, path, train, results, save .blend.",
        epilog="In Blender: blender -b -P scripts/run.py -- --scene DIR --out DIR [options]")
    p.add_argument("--scene", type=Path, required=True, help="LEVIR-NVS or COLMAP scene folder")
    p.add_argument("--out", type=Path, required=True, help="run folder (checkpoint, renders, the .blend)")
    p.add_argument("--preset", choices=choices(PresetName), default="cpu")
    p.add_argument("--method", choices=choices(MethodName), default="dibrgs")
    p.add_argument("--iterations", type=int, default=0, help="0: the preset's")
    p.add_argument("--pseudo-views", type=int, default=0,
                   help="pseudo views sampled along the orbit (0: the preset's number, 96 for cpu)")
    p.add_argument("--fly-frames", type=int, default=0, help="render a fly-through of this many frames (0: none)")
    p.add_argument("--no-init", action="store_true", help="skip the separate initialise step (training runs it)")
    p.add_argument("--python", default=None, help="interpreter with torch and dibrgs_core")
    p.add_argument("--blend", type=Path, default=None, help="output .blend (default OUT/dibrgs.blend)")
    args = p.parse_args(argv)
    if args.iterations < 0 or args.pseudo_views < 0 or args.fly_frames < 0:
        p.error("--iterations, --pseudo-views and --fly-frames must be >= 0")
    if not args.scene.is_dir():
        p.error(f"--scene {args.scene}: not a folder")
    return args


def script_argv() -> list[str]:
    """Arguments meant for this script: after ``--`` inside Blender, else all of them."""
    if "--" in sys.argv:
        return sys.argv[sys.argv.index("--") + 1:]
    return sys.argv[1:] if not Path(sys.argv[0]).name.lower().startswith("blender") else []


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    if args.python:
        os.environ["DIBRGS_PYTHON"] = args.python
    import bpy

    import addon  # top-level package: uses the checkout's dibrgs_core (see addon/_core.py)

    bpy.ops.wm.read_factory_settings(use_empty=True)
    addon.register()
    try:
        scene = bpy.context.scene
        props = scene.dibrgs
        out = args.out.resolve()
        props.work_dir = str(out)
        steps = [("import", lambda: bpy.ops.dibrgs.import_scene(directory=str(args.scene.resolve())))]
        if not args.no_init:
            steps.append(("initialise", lambda: bpy.ops.dibrgs.initialise(blocking=True)))
        steps.append(("train", lambda: bpy.ops.dibrgs.train(blocking=True)))
        if args.fly_frames:
            steps.append(("fly-through", lambda: bpy.ops.dibrgs.flythrough(blocking=True)))
        for name, op in steps:
            if name == "train":  # the import sets the preferences' preset; the command line wins
                props.preset, props.method = args.preset, args.method
                props.iterations, props.pseudo_count = args.iterations, args.pseudo_views
                props.fly_frames = max(args.fly_frames, 2)
            print(f"[DIBR-GS] {name} ...", flush=True)
            try:
                result = op()
            except RuntimeError as e:  # an operator's error report
                print(f"run.py: {name} failed: {e}", file=sys.stderr)
                return 1
            if "FINISHED" not in result:
                print(f"run.py: {name} failed: {props.error or result}", file=sys.stderr)
                return 1
            print(f"[DIBR-GS] {props.message}", flush=True)
        blend = (args.blend or out / "dibrgs.blend").resolve()
        blend.parent.mkdir(parents=True, exist_ok=True)
        bpy.ops.wm.save_as_mainfile(filepath=str(blend))
        print(f"[DIBR-GS] saved {blend}", flush=True)
        return 0
    finally:
        addon.unregister()


if __name__ == "__main__":
    sys.exit(main(script_argv()))
