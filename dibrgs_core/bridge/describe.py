"""Describe a scene folder as JSON for the Blender add-on.

``python -m dibrgs_core.bridge.describe SCENE OUT.json`` reads a LEVIR-NVS or
COLMAP folder with the library's readers (which may need pycolmap, PIL,
tifffile: packages Blender's Python does not have) and writes::

    {"root": str, "views": [{"name", "split": "train"|"test"|"other",
                             "camera": camera_to_dict(...), "image": path|null}],
     "train": [names], "test": [names], "track": [camera dicts]}

Bad input exits with code 2 and an ``InputError`` message on stderr, and
``OUT.json`` is not written.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ..camera.serialize import camera_to_dict
from ..common.errors import InputError
from ..common.fileio import write_json

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".bmp")


def find_image(root: Path, name: str) -> Path | None:
    """The image file of view ``name`` under ``root`` (LEVIR ``Images/``, COLMAP ``images/``)."""
    for folder in ("Images", "images", "Image", "image"):
        d = root / folder
        if not d.is_dir():
            continue
        exact = d / name
        if exact.is_file() and exact.suffix.lower() in IMAGE_SUFFIXES:
            return exact.resolve()
        for suffix in IMAGE_SUFFIXES:
            for cand in (d / (name + suffix), d / (name + suffix.upper())):
                if cand.is_file():
                    return cand.resolve()
    return None


def describe_scene(root: Path) -> dict[str, Any]:
    """The JSON-ready description of the scene at ``root`` (raises InputError)."""
    root = Path(root)
    from ..data.load import read_any_scene

    scene = read_any_scene(root, load_depth=False)
    train, test = list(scene.train), list(scene.test)
    views = []
    for name, view in scene.views.items():
        split = "train" if name in train else "test" if name in test else "other"
        img = find_image(root, name)
        views.append({"name": name, "split": split, "camera": camera_to_dict(view.camera),
                      "image": str(img) if img is not None else None})
    return {"root": str(root.resolve()), "views": views, "train": train, "test": test,
            "track": [camera_to_dict(c) for c in scene.track]}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m dibrgs_core.bridge.describe",
                                description="Describe a scene folder as JSON for the Blender add-on.")
    p.add_argument("scene", type=Path)
    p.add_argument("out", type=Path)
    args = p.parse_args(argv)
    try:
        desc = describe_scene(args.scene)
    except InputError as e:
        print(str(e), file=sys.stderr)
        return 2
    write_json(args.out, desc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
