"""Write a COLMAP scene as a transforms.json scene (the layout of instant-ngp and nerfstudio), to
check that a scene trains alike through either reader (docs/benchmarks.md, "Real flight through a
nerfstudio transforms.json").

    python scripts/colmap_to_transforms.py SCENE OUT [--nerfstudio-axes]

OUT gets ``transforms.json`` (OpenGL camera-to-world matrices; one shared pinhole camera's
``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``), ``images/`` as symbolic links to SCENE's photos
and SCENE's ``split.json`` when it has one. ``--nerfstudio-axes`` permutes the world's axes as
nerfstudio's COLMAP converter does (y and z swapped, z negated). Pinhole models only.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", type=Path, help="COLMAP scene folder (sparse/0 or sparse/ and images/)")
    p.add_argument("out", type=Path, help="folder to write the transforms scene into (must not exist)")
    p.add_argument("--nerfstudio-axes", action="store_true", help="permute the world's axes as nerfstudio does")
    args = p.parse_args(argv)
    import pycolmap

    from dibrgs_core.common.fileio import atomic_path
    from dibrgs_core.data.colmap import find_colmap_model

    model = find_colmap_model(args.scene)
    if model is None:
        p.error(f"{args.scene}: no COLMAP model")
    if args.out.exists():
        p.error(f"{args.out}: exists; give a new folder")
    rec = pycolmap.Reconstruction(str(model))
    cams = {c.model.name for c in rec.cameras.values()}
    if len(rec.cameras) != 1 or not cams <= {"PINHOLE", "SIMPLE_PINHOLE"}:
        p.error(f"{model}: one pinhole camera expected, found {len(rec.cameras)} of models {sorted(cams)}")
    cam = next(iter(rec.cameras.values()))
    K = np.asarray(cam.calibration_matrix())
    (args.out / "images").mkdir(parents=True)
    frames = []
    for im in sorted(rec.images.values(), key=lambda i: i.name):
        w2c = np.eye(4)
        w2c[:3, :4] = im.cam_from_world().matrix()
        c2w = np.linalg.inv(w2c)
        c2w[:3, 1:3] *= -1.0  # OpenCV camera axes -> OpenGL's
        if args.nerfstudio_axes:
            c2w = c2w[[0, 2, 1, 3], :]
            c2w[2, :] *= -1.0
        link = args.out / "images" / im.name
        link.parent.mkdir(parents=True, exist_ok=True)
        os.symlink((args.scene / "images" / im.name).resolve(), link)
        frames.append({"file_path": f"images/{im.name}", "transform_matrix": c2w.tolist()})
    data = {"camera_model": "OPENCV", "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
            "w": cam.width, "h": cam.height, "frames": frames}
    with atomic_path(args.out / "transforms.json") as tmp:
        Path(tmp).write_text(json.dumps(data, indent=1))
    if (args.scene / "split.json").is_file():
        shutil.copyfile(args.scene / "split.json", args.out / "split.json")
    print(f"wrote {len(frames)} frames to {args.out / 'transforms.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
