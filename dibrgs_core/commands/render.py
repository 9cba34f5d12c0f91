"""``dibrgs render WORK --cameras PATH --out DIR``: render any cameras with a trained model.

PATH is a LEVIR-NVS Cams file, a folder of them, a JSON camera list, a COLMAP
model (a scene folder or the model's own folder: its posed images' cameras, at the
photos' full size, undistorted as training reads them), a transforms.json, a
Metashape cameras XML, an OpenDroneMap / OpenSfM reconstruction.json, a Meshroom
cameras.sfm, an OpenMVG sfm_data.json, a Bundler file or RealityCapture XMP sidecars (the folder or one file; likewise). Each camera gives
``DIR/NAME.png`` (named after the camera, e.g. ``002.png`` for ``Cams/002.txt``) and its
z-depth ``DIR/NAME_depth.exr`` (0 where nothing was hit).
``DIR`` has one writer at a time (a second render into it is refused).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from .options import SCENE_LAYOUTS, add_compute, apply_compute, locked


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="render cameras with a trained run", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("work", type=Path, help="run folder of `dibrgs train`")
    p.add_argument("--cameras", type=Path, required=True,
                   help=f"Cams file, folder of Cams files, JSON list, or a scene's cameras ({SCENE_LAYOUTS}; the "
                        "folder or one file)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--no-depth", action="store_true", help="skip the depth EXR files")
    add_compute(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ..common.errors import InputError

    with locked(args.out, "render"):
        apply_compute(args)
        from ..data.images import write_depth_exr, write_png
        from ..data.load import read_any_cameras
        from ..evaluation.evaluate import load_trained

        tr = load_trained(args.work)
        cams = [tr.from_files(c) for c in read_any_cameras(args.cameras)]  # given in the scene's files' frame
        if not cams:
            raise InputError(args.cameras, "no cameras found")
        names = [c.name or f"{i:03d}" for i, c in enumerate(cams)]
        if len(set(names)) != len(names):
            names = [f"{i:03d}_{n}" for i, n in enumerate(names)]
        for cam, name in tqdm(list(zip(cams, names)), desc="render", unit="view", disable=None):
            img, depth = tr.render(cam)
            write_png(args.out / f"{name}.png", img)
            if not args.no_depth:
                write_depth_exr(args.out / f"{name}_depth.exr", depth)
    print(f"rendered {len(cams)} cameras to {args.out}")
    return 0
