"""The hostile catalogue (issue 16): what a hostile but fair user tries, through the real command line.

Every case asserts the exit code, the one-line message (naming the file or option and what to
do, no traceback) and what is left on disk. docs/reliability.md lists the cases with their
verdicts and these test names. Most cases call ``dibrgs_core.cli.main`` in this process (the
command's own parser, commands and error path); what needs another process (a second writer, a
signal, another user's rights, a small or read-only file system) runs ``python -m dibrgs_core``.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from dibrgs_core.common.lock import LOCK_NAME
from dibrgs_core.training.checkpoint import CHECKPOINT, MODEL

from run_synth import QUICK, copy_run, dibrgs, dibrgs_subprocess, finished_run, other_scene24, scene24  # noqa: F401

torch.set_num_threads(1)


def one_line(err: str) -> str:
    """The error line of a command's stderr: exactly one line starting ``dibrgs ...: error:``, no traceback."""
    assert "Traceback" not in err, err
    lines = [x for x in err.splitlines() if ": error: " in x]
    assert len(lines) == 1, err
    return lines[0]


def no_temp_files(folder: Path) -> None:
    left = [p for p in folder.rglob(".*.tmp*")]
    assert not left, left


def strict_json(path: Path):
    def refuse(c):
        raise ValueError(f"{path}: non-strict JSON constant {c}")
    return json.loads(path.read_text(), parse_constant=refuse)


@pytest.fixture()
def scene(scene24, tmp_path) -> Path:
    """A private copy of the 24x24 scene to damage."""
    return Path(shutil.copytree(scene24, tmp_path / "scene"))


@pytest.fixture()
def run(finished_run, tmp_path) -> Path:
    """A private copy of the finished run."""
    return copy_run(finished_run, tmp_path / "run")


# =============================================================================================
# A. Scene files: every malformed input is a clear error naming the file (dibrgs info / train)
# =============================================================================================
def _png_text(s: Path):
    (s / "Images" / "004.png").write_text("not a PNG")


def _png_truncated(s: Path):
    p = s / "Images" / "004.png"
    p.write_bytes(p.read_bytes()[:60])


def _png_empty(s: Path):
    (s / "Images" / "004.png").write_bytes(b"")


def _png_size(s: Path):
    from dibrgs_core.data.images import write_png

    write_png(s / "Images" / "004.png", np.zeros((24, 25, 3)))


def _cams_edit(old: str, new: str):
    def f(s: Path):
        p = s / "Cams" / "004.txt"
        p.write_text(p.read_text().replace(old, new, 1))
    return f


def _cams_replace_first_row(row: str):
    def f(s: Path):
        p = s / "Cams" / "004.txt"
        lines = p.read_text().splitlines()
        lines[1] = row
        p.write_text("\n".join(lines))
    return f


def _cams_values(s: Path):
    p = s / "Cams" / "004.txt"
    p.write_text(p.read_text() + "\n1.0\n")


def _no_cam(s: Path):
    (s / "Cams" / "004.txt").unlink()


def _no_image(s: Path):
    (s / "Images" / "004.png").unlink()


def _no_images_dir(s: Path):
    shutil.rmtree(s / "Images")


def _depth_missing(s: Path):
    (s / "Depths" / "004.tiff").unlink()


def _depth_corrupt(s: Path):
    (s / "Depths" / "004.tiff").write_bytes(b"II*\x00garbage")


def _depth_size(s: Path):
    from dibrgs_core.data.images import write_depth_tiff

    write_depth_tiff(s / "Depths" / "004.tiff", np.ones((5, 5), np.float32))


def _split_json(text: str):
    def f(s: Path):
        (s / "split.json").write_text(text)
    return f


SCENE_CASES = [
    # id, damage, what the message says, the file it names
    ("image-not-an-image", _png_text, "unreadable", "Images/004.png"),
    ("image-truncated", _png_truncated, "truncated", "Images/004.png"),
    ("image-empty", _png_empty, "unreadable", "Images/004.png"),
    ("image-other-size", _png_size, "25x24 but", "Images/004.png"),
    ("image-missing", _no_image, "image missing for camera", "Images/004.png"),
    ("images-folder-missing", _no_images_dir, "missing folder", "Images"),
    ("cams-missing", _no_cam, "camera file missing", "Cams/004.txt"),
    ("cams-nan", _cams_replace_first_row("nan 0 0 0"), "NaN or infinite", "Cams/004.txt"),
    ("cams-token", _cams_edit("intrinsic", "intrinsic x"), "unexpected token", "Cams/004.txt"),
    ("cams-no-intrinsic", _cams_edit("intrinsic", "intrinsik"), "'extrinsic' and 'intrinsic'", "Cams/004.txt"),
    ("cams-count", _cams_values, "DEPTH_MIN DEPTH_MAX", "Cams/004.txt"),
    ("cams-singular", _cams_replace_first_row("0 0 0 0"), "singular", "Cams/004.txt"),
    ("cams-reflection", _cams_replace_first_row("-1 0 0 0"), "not a rotation", "Cams/004.txt"),
    ("depth-missing", _depth_missing, "depth map missing", "Depths/004.tiff"),
    ("depth-corrupt", _depth_corrupt, "unreadable depth map", "Depths/004.tiff"),
    ("depth-other-size", _depth_size, "depth map is 5x5", "Depths/004.tiff"),
    ("split-not-json", _split_json("{train: oops"), "unreadable split file", "split.json"),
    ("split-not-object", _split_json("[1, 2]"), "expected an object", "split.json"),
    ("split-unknown-name", _split_json('{"train": ["001", "999"], "test": ["002"]}'), "'999' not in the scene",
     "split.json"),
    ("split-overlap", _split_json('{"train": ["001", "002"], "test": ["002", "003"]}'),
     "in both the training and the test set", "split.json"),
]


@pytest.mark.parametrize("damage,says,names", [c[1:] for c in SCENE_CASES], ids=[c[0] for c in SCENE_CASES])
def test_scene_file_faults(scene, damage, says, names):
    """A damaged scene: `dibrgs info` exits 2 with one line naming the file; nothing is written."""
    damage(scene)
    before = sorted(p.relative_to(scene) for p in scene.rglob("*"))
    rc, err = dibrgs("info", scene)
    line = one_line(err)
    assert rc == 2 and says in line and str(scene / names) in line, err
    assert sorted(p.relative_to(scene) for p in scene.rglob("*")) == before


def test_scene_folder_missing_or_a_file(tmp_path):
    rc, err = dibrgs("info", tmp_path / "nope")
    assert rc == 2 and "scene folder not found" in one_line(err)
    f = tmp_path / "f.txt"
    f.write_text("x")
    rc, err = dibrgs("train", f, "--out", tmp_path / "w", *QUICK)
    assert rc == 2 and str(f) in one_line(err) and not (tmp_path / "w").exists()
    rc, err = dibrgs("info", tmp_path)
    assert rc == 2 and "not a scene" in one_line(err)


def test_unknown_view_names_on_the_command_line(scene, tmp_path):
    rc, err = dibrgs("train", scene, "--out", tmp_path / "w", *QUICK, "--train", "001,nope")
    line = one_line(err)
    assert rc == 2 and "--train: 'nope' not in the scene" in line and "001" in line
    rc, err = dibrgs("info", scene, "--train", "001,002", "--test", "002")
    assert rc == 2 and "in both the training and the test set" in one_line(err)
    assert not (tmp_path / "w").exists()  # nothing left behind by a refused run


# COLMAP models
@pytest.fixture()
def colmap(scene24, tmp_path) -> Path:
    from dibrgs_core.data.colmap import write_colmap_model
    from dibrgs_core.data.levir import read_scene

    sc = read_scene(scene24, load_depth=False)
    root = tmp_path / "colmap"
    write_colmap_model(sc.cameras, root / "sparse" / "0", binary=True)
    (root / "images").mkdir()
    for name in sc.views:
        shutil.copy(scene24 / "Images" / f"{name}.png", root / "images" / f"{name}.png")
    return root


def _fisheye(root: Path):
    import pycolmap

    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    c = rec.cameras[1]
    rec.cameras[1] = pycolmap.Camera(model="OPENCV_FISHEYE", width=c.width, height=c.height,
                                     params=[c.params[0], c.params[1], c.params[2], c.params[3], 0.1, 0, 0, 0],
                                     camera_id=1)
    rec.write_binary(str(root / "sparse" / "0"))


COLMAP_CASES = [
    ("model-file-missing", lambda r: (r / "sparse/0/images.bin").unlink(), "COLMAP model file missing",
     "sparse/0/images.bin"),
    ("model-corrupt", lambda r: (r / "sparse/0/cameras.bin").write_bytes(b"\x01\x02garbage"),
     "unreadable COLMAP model", "sparse/0"),
    ("photo-missing", lambda r: (r / "images/004.png").unlink(), "image file missing", "images/004.png"),
    ("photo-other-size", lambda r: _png_size_at(r / "images/004.png"), "25x24 but its COLMAP camera is 24x24",
     "images/004.png"),
    ("images-folder-missing", lambda r: shutil.rmtree(r / "images"), "image folder not found", "images"),
    ("fisheye", _fisheye, "OPENCV_FISHEYE is a fisheye model", "sparse/0"),
]


def _png_size_at(p: Path):
    from dibrgs_core.data.images import write_png

    write_png(p, np.zeros((24, 25, 3)))


@pytest.mark.parametrize("damage,says,names", [c[1:] for c in COLMAP_CASES], ids=[c[0] for c in COLMAP_CASES])
def test_colmap_faults(colmap, damage, says, names):
    damage(colmap)
    rc, err = dibrgs("info", colmap)
    line = one_line(err)
    assert rc == 2 and says in line and str(colmap / names) in line, err


# =============================================================================================
# B. Option values refused when the command line is parsed (exit 2, one line naming the option)
# =============================================================================================
OPTION_CASES = [
    ("resolution-scale-0", ["train", "S", "--out", "W", "--resolution-scale", "0"], "--resolution-scale: must be in (0, 4]"),
    ("resolution-scale-negative", ["train", "S", "--out", "W", "--resolution-scale", "-1"], "--resolution-scale: must be in (0, 4]"),
    ("resolution-scale-huge", ["train", "S", "--out", "W", "--resolution-scale", "5"], "--resolution-scale: must be in (0, 4]"),
    ("resolution-scale-nan", ["train", "S", "--out", "W", "--resolution-scale", "nan"], "--resolution-scale: must be a finite"),
    ("iterations-0", ["train", "S", "--out", "W", "--iterations", "0"], "--iterations: must be a positive integer"),
    ("iterations-text", ["train", "S", "--out", "W", "--iterations", "many"], "--iterations: expected an integer"),
    ("seed-negative", ["train", "S", "--out", "W", "--seed", "-1"], "--seed: must be in [0, 2^32)"),
    ("threads-0", ["eval", "W", "--threads", "0"], "--threads: must be a positive integer"),
    ("demo-resolution-0", ["demo", "--resolution", "0"], "--resolution: must be at least 8 pixels"),
    ("demo-resolution-4", ["demo", "--resolution", "4"], "--resolution: must be at least 8 pixels"),
    ("fps-repeats-0", ["eval", "W", "--fps-repeats", "0"], "--fps-repeats: must be a positive integer"),
    ("voxel-negative", ["init", "S", "--out", "W", "--voxel", "-1"], "--voxel: must be >= 0"),
    ("scale-0", ["init", "S", "--out", "W", "--scale", "0"], "--scale: must be > 0"),
    ("empty-train-list", ["train", "S", "--out", "W", "--train", ","], "--train: expected comma-separated"),
]


@pytest.mark.parametrize("argv,says", [c[1:] for c in OPTION_CASES], ids=[c[0] for c in OPTION_CASES])
def test_bad_option_values(tmp_path, argv, says):
    argv = [str(tmp_path / a) if a in ("S", "W") else a for a in argv]
    rc, err = dibrgs(*argv)
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and says in lines[0] and "--help" in lines[0], err
    assert not (tmp_path / "W").exists()


def test_resolution_scale_too_small_for_the_images(scene, tmp_path):
    """0.1 x 24 px = 2 px: refused once the images' size is known, naming the option."""
    rc, err = dibrgs("train", scene, "--out", tmp_path / "w", *QUICK, "--resolution-scale", "0.1")
    line = one_line(err)
    assert rc == 2 and "--resolution-scale 0.1 gives 2x2 images" in line
    assert not (tmp_path / "w" / MODEL).exists() and not (tmp_path / "w" / CHECKPOINT).exists()


@pytest.mark.parametrize("extra", [[], ["--no-pseudo"]], ids=["pseudo", "no-pseudo"])
def test_one_training_view_is_refused(scene, tmp_path, extra):
    """One training view (with or without pseudo views) is refused before anything is trained."""
    rc, err = dibrgs("train", scene, "--out", tmp_path / "w", *QUICK, "--train", "001", *extra)
    line = one_line(err)
    assert rc == 2 and "1 training view (001; split from --train" in line and "at least 2" in line
    assert not (tmp_path / "w" / MODEL).exists()
    (scene / "split.json").write_text('{"train": ["008"], "test": ["009"]}')
    rc, err = dibrgs("init", scene, "--out", tmp_path / "w2", "--threads", "1")
    assert rc == 2 and "split.json" in one_line(err) and not (tmp_path / "w2" / "init").exists()


def test_debug_shows_the_traceback(tmp_path):
    rc, err = dibrgs("eval", tmp_path / "nope")
    assert rc == 2 and "Traceback" not in err and "no trained model" in one_line(err)
    rc, err = dibrgs("eval", tmp_path / "nope", "--debug")
    assert rc == 2 and "Traceback" in err and "no trained model" in err.strip().splitlines()[-1]


def test_threads_default_to_the_available_cores():
    from dibrgs_core.cli import build_parser
    from dibrgs_core.commands.options import apply_threads, available_cores

    n = torch.get_num_threads()
    try:
        for cmd in (["train", "S", "--out", "W"], ["init", "S", "--out", "W"], ["eval", "W"],
                    ["render", "W", "--cameras", "C", "--out", "O"], ["export", "W", "--ply", "P"], ["demo"]):
            args = build_parser().parse_args(cmd)
            assert args.threads is None, cmd
            assert apply_threads(args) == available_cores() == len(os.sched_getaffinity(0))
            assert torch.get_num_threads() == available_cores()
            args = build_parser().parse_args(cmd + ["--threads", "1"])
            assert apply_threads(args) == 1 and torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(n)
