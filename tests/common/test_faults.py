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
import random
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from dibrgs_core.common.lock import LOCK_NAME
from dibrgs_core.data.ply import read_ply
from dibrgs_core.training.checkpoint import CHECKPOINT, MODEL

from run_synth import QUICK, copy_run, dibrgs, dibrgs_subprocess
from threads import torch_threads

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

    write_png(s / "Images" / "004.png", np.zeros((48, 50, 3)))  # resized by mistake: its camera is for 24x24


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
    ("image-other-size", _png_size, "50x48 but its camera's principal point (12, 12) lies off", "Images/004.png"),
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
    ("camera-missing", lambda r: _first_image_camera(r / "sparse/0/images.bin", 77),
     "image 000.png refers to camera 77, which is not in the model", "sparse/0"),
]


def _first_image_camera(images_bin: Path, camera_id: int):
    """Set the camera id of the first image of a binary model (after the count, the image's id and
    its pose: COLMAP's reconstruction_io_binary.cc)."""
    data = bytearray(images_bin.read_bytes())
    struct.pack_into("<I", data, 8 + 4 + 56, camera_id)
    images_bin.write_bytes(bytes(data))


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
    from dibrgs_core.commands.options import apply_compute, available_cores

    with torch_threads(torch.get_num_threads()):  # the commands set the count; restored after
        for cmd in (["train", "S", "--out", "W"], ["init", "S", "--out", "W"], ["eval", "W"],
                    ["render", "W", "--cameras", "C", "--out", "O"], ["export", "W", "--ply", "P"], ["demo"]):
            args = build_parser().parse_args(cmd)
            assert args.threads is None, cmd
            assert apply_compute(args) == available_cores() == len(os.sched_getaffinity(0))
            assert torch.get_num_threads() == available_cores()
            args = build_parser().parse_args(cmd + ["--threads", "1"])
            assert apply_compute(args) == 1 and torch.get_num_threads() == 1


# =============================================================================================
# C. The run folder: one writer, caches that know their inputs, resume that checks its flags
# =============================================================================================
def _config(work: Path) -> dict:
    return strict_json(work / "config.json")


def _model_cfg(work: Path) -> dict:
    return torch.load(work / MODEL, map_location="cpu", weights_only=False)["config"]


@pytest.mark.slow
def test_two_writers_one_gets_the_lock_error(scene24, finished_run, tmp_path):
    """Two `dibrgs train` into one folder, in two processes: the second exits 75 naming the first (pid,
    host) and writes nothing; the first finishes, and config.json and model.pt both hold its seed."""
    work = copy_run(finished_run, tmp_path / "w")
    first = subprocess.Popen([sys.executable, "-m", "dibrgs_core", "train", str(scene24), "--out", str(work), *QUICK,
                              "--iterations", "6", "--seed", "0"], stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[2])
    try:
        lock = work / LOCK_NAME
        t0 = time.monotonic()
        while not (lock.exists() and str(first.pid) in lock.read_text()):
            assert first.poll() is None and time.monotonic() - t0 < 120, "the first writer never took the lock"
            time.sleep(0.05)
        os.kill(first.pid, signal.SIGSTOP)  # hold it inside the run, whatever the machine's speed
        try:  # the second writer: this test's own process, through the same command line
            rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "6", "--seed", "1")
        finally:
            os.kill(first.pid, signal.SIGCONT)
        line = one_line(err)
        assert rc == 75, err
        assert f"in use by pid {first.pid} on {socket.gethostname()} (train" in line and str(work) in line
        assert first.wait(timeout=300) == 0, first.stderr.read()[-2000:]
    finally:
        if first.poll() is None:
            first.kill()
    assert _config(work)["config"]["seed"] == 0 and _model_cfg(work)["seed"] == 0
    assert "seed 1" not in (work / "train.log").read_text() and not lock.exists()


def test_a_stale_lock_is_taken_over(scene24, finished_run, tmp_path, caplog):
    """A writer killed with SIGKILL leaves its lock file; the next writer takes it over and says whose it was."""
    work = copy_run(finished_run, tmp_path / "w")
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from dibrgs_core.common.lock import acquire; "
                               "acquire(sys.argv[1], 'train'); print('locked', flush=True); time.sleep(600)",
                               str(work)], stdout=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[2])
    assert holder.stdout.readline().strip() == "locked"
    rc, err = dibrgs("eval", work, "--threads", "1", "--fps-repeats", "1")
    assert rc == 75 and f"pid {holder.pid}" in one_line(err)
    holder.kill()
    holder.wait()
    assert str(holder.pid) in (work / LOCK_NAME).read_text()  # left behind
    with caplog.at_level("INFO", logger="dibrgs"):
        rc, err = dibrgs("eval", work, "--threads", "1", "--fps-repeats", "1")
    assert rc == 0, err
    assert f"taking over the stale lock of pid {holder.pid}" in caplog.text
    assert not (work / LOCK_NAME).exists()


def test_render_into_a_busy_folder_and_init_into_a_busy_run(scene24, finished_run, tmp_path):
    """The lock covers init, eval and render too (the add-on's jobs run these commands)."""
    from dibrgs_core.common.lock import run_folder_lock

    work = copy_run(finished_run, tmp_path / "w")
    out = tmp_path / "renders"
    with run_folder_lock(out, "render"):
        r = dibrgs_subprocess("render", work, "--cameras", scene24 / "Cams" / "002.txt", "--out", out)
        assert r.returncode == 75 and "in use by pid" in one_line(r.stderr)
    with run_folder_lock(work, "train"):
        r = dibrgs_subprocess("init", scene24, "--out", work)
        assert r.returncode == 75 and "in use by pid" in one_line(r.stderr)
    assert not list(out.glob("*.png"))


def test_another_scene_replaces_the_run_and_its_caches(other_scene24, finished_run, tmp_path, caplog):
    """`train OTHER --out W` over an earlier run: reported and replaced; the geometry, SfM points and pseudo
    views are made again from OTHER (never "reusing the geometry initialisation")."""
    from dibrgs_core.data.load import load_scene
    from dibrgs_core.geometry.pipeline import InitConfig, init_inputs

    work = copy_run(finished_run, tmp_path / "w")
    old_pseudo = strict_json(work / "pseudo" / "manifest.json")["hash"]
    with caplog.at_level("INFO", logger="dibrgs"):
        rc, err = dibrgs("train", other_scene24, "--out", work, *QUICK, "--iterations", "2")
    assert rc == 0, err
    assert "held a run of another scene" in caplog.text and "reusing the geometry" not in caplog.text
    other = load_scene(other_scene24)
    assert _config(work)["run"]["digest"] == other.digest()
    assert strict_json(work / "init" / "init_report.json")["values"]["inputs"] == init_inputs(other, InitConfig())
    assert strict_json(work / "pseudo" / "manifest.json")["hash"] != old_pseudo
    assert _model_cfg(work)["iterations"] == 2


def test_resume_refuses_another_scenes_run(other_scene24, finished_run, tmp_path):
    work = copy_run(finished_run, tmp_path / "w")
    before = (work / CHECKPOINT).read_bytes()
    rc, err = dibrgs("train", other_scene24, "--out", work, *QUICK, "--iterations", "8", "--resume")
    line = one_line(err)
    assert rc == 2 and "run here is of another scene" in line and "drop --resume to replace it" in line
    assert (work / CHECKPOINT).read_bytes() == before and (work / MODEL).exists()


def test_init_of_another_split_is_not_reused(scene24, tmp_path, caplog):
    """`init --train 002,009` then `train` with the default split: the initialisation is made again
    from 001/008/015 (and the split is in report.json and the log)."""
    work = tmp_path / "w"
    rc, err = dibrgs("init", scene24, "--out", work, "--train", "2,9", "--threads", "1")
    assert rc == 0, err
    assert strict_json(work / "init" / "init_report.json")["values"]["train"] == ["002", "009"]
    with caplog.at_level("INFO", logger="dibrgs"):
        rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "2", "--no-pseudo")
    assert rc == 0, err
    assert "made from other training views; initialising again" in caplog.text
    assert strict_json(work / "init" / "init_report.json")["values"]["train"] == ["001", "008", "015"]
    scene = strict_json(work / "report.json")["values"]["scene"]
    assert scene["train"] == ["001", "008", "015"] and scene["split_source"] == "default (LEVIR-NVS 3-view protocol)"
    assert "split from default (LEVIR-NVS 3-view protocol)" in (work / "train.log").read_text()


def test_init_with_another_depth_prior_is_not_reused(scene24, tmp_path, caplog):
    """`init --depth-prior gt` (the oracle) then `train` with the default prior: the geometry is
    made again with the weight-free one, never the oracle's cloud reused; `train --depth-prior gt`
    after that makes it again as well."""
    work = tmp_path / "w"
    rc, err = dibrgs("init", scene24, "--out", work, "--depth-prior", "gt", "--threads", "1")
    assert rc == 0, err
    assert strict_json(work / "init" / "init_report.json")["values"]["config"]["depth_prior"] == "gt"
    for prior, want in ((None, "auto"), ("gt", "gt")):
        caplog.clear()
        with caplog.at_level("INFO", logger="dibrgs"):
            rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "2", "--no-pseudo",
                             *(["--depth-prior", prior] if prior else []))
        assert rc == 0, err
        assert "made with another depth prior; initialising again" in caplog.text, prior
        assert "reusing the geometry initialisation" not in caplog.text
        assert strict_json(work / "init" / "init_report.json")["values"]["config"]["depth_prior"] == want


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["report-not-json", "points-truncated", "height-map-garbage"])
def test_a_damaged_geometry_cache_is_made_again(scene24, finished_run, tmp_path, caplog, damage):
    """A run folder's ``init/`` damaged after the fact (a disk error, a hand edit): ``train`` says
    so and initialises again, instead of failing or training on half a cloud."""
    work = copy_run(finished_run, tmp_path / "w")
    init = work / "init"
    good = read_ply(init / "points.ply")[0]
    if damage == "report-not-json":
        (init / "init_report.json").write_text("{not json")
    elif damage == "points-truncated":
        ply = init / "points.ply"
        ply.write_bytes(ply.read_bytes()[: ply.stat().st_size // 2])
    else:
        assert (init / "height_map.npz").exists()
        (init / "height_map.npz").write_bytes(b"PK not a zip")
    with caplog.at_level("INFO", logger="dibrgs"):
        rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "2", "--no-pseudo")
    assert rc == 0, err
    assert "initialising again" in caplog.text and "reusing the geometry initialisation" not in caplog.text
    strict_json(init / "init_report.json")
    assert np.array_equal(read_ply(init / "points.ply")[0], good)


RESUME_REFUSED = [
    ("preset", ["--preset", "cpu"], "preset: 'test' -> 'cpu'"),
    ("seed", ["--seed", "1"], "seed: 0 -> 1"),
    ("no-pseudo", ["--no-pseudo"], "pseudo.mode: 'auto' -> 'off'"),
    ("resolution", ["--resolution-scale", "0.5"], "resolution_scale: None -> 0.5"),
]


@pytest.mark.parametrize("flags,lists", [c[1:] for c in RESUME_REFUSED], ids=[c[0] for c in RESUME_REFUSED])
def test_resume_refuses_changed_options(scene24, finished_run, tmp_path, flags, lists):
    work = copy_run(finished_run, tmp_path / "w")
    before = {p.name: p.read_bytes() for p in (work / CHECKPOINT, work / MODEL, work / "config.json")}
    preset = flags[1] if flags[0] == "--preset" else "test"
    flags = [] if flags[0] == "--preset" else flags
    rc, err = dibrgs("train", scene24, "--out", work, "--preset", preset, "--threads", "1", "--iterations", "6",
                     "--resume", *flags)
    line = one_line(err)
    assert rc == 2 and lists in line and "--force-config" in line and str(work / CHECKPOINT) in line, err
    assert {n: (work / n).read_bytes() for n in before} == before


@pytest.mark.parametrize("flags,lists", [(["--ibr", "none"], "ibr: 'auto' -> 'none'"),
                                         (["--iterations", "3"], "iterations: 6 -> 3"),
                                         (["--method", "3dgs"], "method: 'dibrgs' -> '3dgs'")],
                         ids=["ibr", "fewer-iterations", "method"])
def test_resume_changes_no_checkpoint_can_follow(scene24, finished_run, tmp_path, flags, lists):
    """Changes of the model's make-up, or fewer iterations than done, are refused even with --force-config."""
    work = copy_run(finished_run, tmp_path / "w")
    argv = ["train", scene24, "--out", work, *QUICK, "--resume", "--force-config"]
    if "--iterations" not in flags:
        argv += ["--iterations", "6"]
    rc, err = dibrgs(*argv, *flags)
    line = one_line(err)
    assert rc == 2 and "cannot resume with" in line and lists in line, err
    assert _model_cfg(work)["iterations"] == 6


def test_resume_with_more_iterations_goes_on(scene24, finished_run, tmp_path, caplog):
    work = copy_run(finished_run, tmp_path / "w")
    with caplog.at_level("INFO", logger="dibrgs"):
        rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "8", "--resume")
    assert rc == 0, err
    assert _model_cfg(work)["iterations"] == 8 and _config(work)["config"]["iterations"] == 8
    rep = strict_json(work / "report.json")["values"]
    assert rep["resumed_from"] == 6 and rep["iteration"] == 8 and rep["resume_changes"] == [["iterations", 6, 8]]
    assert "resuming with changed iterations: 6 -> 8" in (work / "train.log").read_text()


def test_resume_may_change_the_curve_interval(scene24, finished_run, tmp_path):
    """``--curve-every`` on ``--resume`` is a safe change, listed in the report, and the next
    point follows the new interval at once (0: a point after every iteration), not the point the
    old interval had scheduled."""
    from dibrgs_core.bench.runner import read_curve

    work = copy_run(finished_run, tmp_path / "w")
    before = [p["iteration"] for p in read_curve(work / "curve.csv")]
    assert before[-1] == 6 and 7 not in before
    rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "9", "--resume", "--curve-every", "0")
    assert rc == 0, err
    assert [p["iteration"] for p in read_curve(work / "curve.csv")] == before + [7, 8, 9]
    rep = strict_json(work / "report.json")["values"]
    assert ["curve_every_s", 10.0, 0.0] in rep["resume_changes"] and "forced_config" not in rep
    assert _config(work)["config"]["curve_every_s"] == 0.0


def test_a_finished_runs_last_point_is_scored_again_on_the_points_views(scene24, finished_run, tmp_path, caplog):
    """A finished run's last curve point scores every held-out view, the others a subset. When the
    run goes on, that point becomes an ordinary one: scored again on the subset, which the finished
    run's report gives as ``final_psnr_on_point_views``, so that the earlier points all compare."""
    from dibrgs_core.bench.runner import read_curve

    work = copy_run(finished_run, tmp_path / "w")
    old = read_curve(work / "curve.csv")
    rep = strict_json(work / "report.json")["values"]["curve"]
    assert rep["views_final"] > rep["views_per_point"]
    assert old[-1]["iteration"] == 6 and abs(old[-1]["psnr"] - rep["final_psnr_on_point_views"]) > 1e-4
    with caplog.at_level("INFO", logger="dibrgs"):
        rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "8", "--resume", "--curve-every", "0")
    assert rc == 0, err
    new = read_curve(work / "curve.csv")
    assert [p["iteration"] for p in new] == [p["iteration"] for p in old] + [7, 8]
    assert new[:len(old) - 1] == old[:-1] and new[len(old) - 1]["seconds"] == old[-1]["seconds"]
    assert new[len(old) - 1]["psnr"] == pytest.approx(rep["final_psnr_on_point_views"], abs=1e-4)
    assert "scored again on the 4 held-out views" in caplog.text


def test_force_config_accepts_and_records(scene24, finished_run, tmp_path):
    work = copy_run(finished_run, tmp_path / "w")
    rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "8", "--seed", "3", "--resume",
                     "--force-config")
    assert rc == 0, err
    assert _model_cfg(work)["seed"] == 3
    forced = strict_json(work / "report.json")["values"]["forced_config"]
    assert forced == [{"iteration": 6, "changes": [["seed", 0, 3]]}]
    assert _config(work)["forced_config"] == forced
    rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--force-config")
    assert rc == 2 and "--force-config only applies with --resume" in one_line(err)
    rc, err = dibrgs("train", scene24, "--out", tmp_path / "p", *QUICK, "--pseudo-views", "3",
                     "--pseudo-path", work / "nowhere.json")
    assert rc == 2 and "--pseudo-views does not apply with --pseudo-path" in one_line(err)
    assert not (tmp_path / "p").exists()
    # A path that holds no cameras is refused before the geometry stage runs.
    rc, err = dibrgs("train", scene24, "--out", tmp_path / "q", *QUICK, "--pseudo-path", work / "nowhere.json")
    assert rc == 2 and "nowhere.json: camera path not found" in one_line(err)
    assert not (tmp_path / "q" / "init").exists()


def test_resume_refuses_another_split(scene24, finished_run, tmp_path):
    work = copy_run(finished_run, tmp_path / "w")
    rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "6", "--resume", "--train", "1,8")
    line = one_line(err)
    assert rc == 2 and "another split" in line and "train ['001', '008', '015'] -> ['001', '008']" in line


def test_a_fresh_run_replaces_the_earlier_runs_outputs(scene24, finished_run, tmp_path, caplog):
    """Without --resume the earlier run's outputs go first (no mix of two runs); its caches stay."""
    work = copy_run(finished_run, tmp_path / "w")
    rc, err = dibrgs("eval", work, "--threads", "1", "--fps-repeats", "1")
    assert rc == 0 and (work / "metrics.json").exists() and (work / "renders").is_dir()
    keep = work / "notes.txt"
    keep.write_text("the user's own file")
    with caplog.at_level("INFO", logger="dibrgs"):
        rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "3")
    assert rc == 0, err
    assert "starting afresh (no --resume)" in (work / "train.log").read_text()
    assert not (work / "metrics.json").exists() and not (work / "renders").exists()
    assert _model_cfg(work)["iterations"] == 3 and keep.read_text() == "the user's own file"
    assert (work / "init" / "points.ply").exists()
    assert "train.log" in [p.name for p in work.iterdir()] and "iteration 6" not in (work / "train.log").read_text()


# =============================================================================================
# D. The operating system says no: one line naming the path and what to do, exit 1 (2 for input)
# =============================================================================================
@pytest.mark.parametrize("what", ["empty", "truncated", "corrupt", "corrupt_no_message", "foreign", "keys_missing",
                                  "config_damaged", "iteration_damaged"])
def test_unreadable_checkpoint(scene24, finished_run, tmp_path, what):
    work = copy_run(finished_run, tmp_path / "w")
    ck = work / CHECKPOINT
    data = ck.read_bytes()
    # These bytes make torch.load raise a MemoryError without a message (about one random 4 KiB file
    # in 300 does; the error line then failed to format and came out as an internal error).
    no_message = random.Random(454).randbytes(4096)
    ck.write_bytes({"empty": b"", "truncated": data[: len(data) // 2], "corrupt": os.urandom(4096),
                    "corrupt_no_message": no_message}.get(what, b""))
    if what == "foreign":
        torch.save([1, 2, 3], ck)
    elif what in ("keys_missing", "config_damaged", "iteration_damaged"):  # a dict, but not what a run wrote
        st = torch.load(finished_run / CHECKPOINT, weights_only=False)
        if what == "keys_missing":
            del st["rng"], st["report"]
        elif what == "config_damaged":
            st["config"]["iterations"] = "many"
        else:
            st["iteration"] = "6"
        torch.save(st, ck)
    before = ck.read_bytes()
    rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "6", "--resume")
    line = one_line(err)
    assert rc == 2 and str(ck) in line and "delete it to start afresh" in line, err
    assert ck.read_bytes() == before and (work / MODEL).exists()


@pytest.mark.parametrize("what", ["empty", "truncated"])
def test_unreadable_model_file(finished_run, tmp_path, what):
    work = copy_run(finished_run, tmp_path / "w")
    m = work / MODEL
    m.write_bytes(b"" if what == "empty" else m.read_bytes()[:1000])
    for argv in (["eval", work], ["export", work, "--ply", tmp_path / "g.ply"],
                 ["render", work, "--cameras", work / "x.json", "--out", tmp_path / "r"]):
        rc, err = dibrgs(*argv, "--threads", "1")
        line = one_line(err)
        assert rc == 2 and str(m) in line and ("empty" in line or "unreadable trained model" in line), err
    assert not (tmp_path / "g.ply").exists() and not (work / "metrics.json").exists()


def test_a_model_file_of_another_kind(finished_run, tmp_path):
    """A readable model.pt without what a run writes (another tool's dict): one line naming the file."""
    work = copy_run(finished_run, tmp_path / "w")
    m = work / MODEL
    torch.save({"method": "dibrgs", "weights": [1, 2]}, m)
    rc, err = dibrgs("eval", work, "--threads", "1")
    line = one_line(err)
    assert rc == 2 and str(m) in line and "cannot read the trained model (KeyError" in line, err
    assert not (work / "metrics.json").exists()


@pytest.mark.slow
@pytest.mark.parametrize("name,damaged", [("report.json", {"values": []}), ("config.json", {"run": [1, 2]}),
                                          ("config.json", {"run": {"resolution_scale": "x"}})],
                         ids=["report-values-a-list", "config-run-a-list", "config-scale-a-word"])
def test_eval_of_a_run_with_damaged_records(scene24, finished_run, tmp_path, name, damaged):
    """A run folder's report.json or config.json damaged (values of another type): ``eval`` still
    scores the model (what it cannot read left out or found again) instead of a traceback."""
    work = copy_run(finished_run, tmp_path / "w")
    (work / name).write_text(json.dumps(damaged))
    rc, err = dibrgs("eval", work, "--scene", scene24, "--threads", "1")
    assert rc == 0, err
    assert json.loads((work / "metrics.json").read_text())["psnr"] > 0


def test_eval_after_the_scene_moved(scene24, other_scene24, finished_run, tmp_path):
    """A run folder outlives its scene's place (another disk, a colleague's machine): ``eval`` says
    to give the new folder, ``--scene`` evaluates there, and another scene is refused by content."""
    work = copy_run(finished_run, tmp_path / "w")
    st = torch.load(work / MODEL, weights_only=False)
    old = tmp_path / "old_place"
    st["scene"] = str(Path(shutil.copytree(scene24, old)).resolve())
    torch.save(st, work / MODEL)
    new = Path(shutil.move(old, tmp_path / "new place"))
    rc, err = dibrgs("eval", work, "--threads", "1")
    line = one_line(err)
    assert rc == 2 and str(old) in line and "--scene" in line and not (work / "metrics.json").exists()
    rc, err = dibrgs("eval", work, "--scene", new, "--threads", "1")
    assert rc == 0, err
    m = strict_json(work / "metrics.json")
    ref = copy_run(finished_run, tmp_path / "ref")  # the same run evaluated where it trained
    rc, err = dibrgs("eval", ref, "--threads", "1", "--fps-repeats", "1")
    assert rc == 0, err
    assert m["psnr"] == pytest.approx(strict_json(ref / "metrics.json")["psnr"], abs=1e-9)
    # Another scene with the same view names: refused by its content, metrics left as they were.
    rc, err = dibrgs("eval", work, "--scene", other_scene24, "--threads", "1")
    assert rc == 2 and "not the scene" in one_line(err) and strict_json(work / "metrics.json") == m
    rc, err = dibrgs("eval", work, "--scene", tmp_path / "nowhere", "--threads", "1")
    assert rc == 2 and "--scene: no such folder" in one_line(err)


def test_out_is_a_file_or_under_a_file(scene24, finished_run, tmp_path):
    f = tmp_path / "file"
    f.write_text("keep me")
    rc, err = dibrgs("train", scene24, "--out", f, *QUICK)
    assert rc == 2 and f"{f}: is a file, not a folder" in one_line(err)
    rc, err = dibrgs("train", scene24, "--out", f / "sub", *QUICK)
    assert rc == 1 and "a part of this path is a file, not a folder" in one_line(err)
    rc, err = dibrgs("render", finished_run, "--cameras", scene24 / "Cams" / "002.txt", "--out", f, "--threads", "1")
    assert rc == 2 and f"{f}: is a file, not a folder" in one_line(err)
    rc, err = dibrgs("init", scene24, "--out", f, "--threads", "1")
    assert rc == 2 and "is a file" in one_line(err)
    assert f.read_text() == "keep me"


def test_export_targets(finished_run, tmp_path):
    """--ply a folder or a FIFO: refused, left as they are; a symbolic link: the file it points to is
    written and the link stays; new files get the umask's mode, replaced files keep theirs."""
    d = tmp_path / "folder"
    d.mkdir()
    rc, err = dibrgs("export", finished_run, "--ply", d, "--threads", "1")
    assert rc == 2 and f"{d}: is a folder, not a regular file" in one_line(err) and d.is_dir()
    fifo = tmp_path / "pipe.ply"
    os.mkfifo(fifo)
    rc, err = dibrgs("export", finished_run, "--ply", fifo, "--threads", "1")
    assert rc == 2 and "is a FIFO (named pipe), not a regular file" in one_line(err)
    assert stat_kind(fifo) == "fifo"
    target = tmp_path / "real" / "g.ply"
    target.parent.mkdir()
    target.write_text("old")
    os.chmod(target, 0o640)
    link = tmp_path / "link.ply"
    link.symlink_to(target)
    rc, err = dibrgs("export", finished_run, "--ply", link, "--threads", "1")
    assert rc == 0, err
    assert link.is_symlink() and target.read_bytes().startswith(b"ply\n")
    assert (target.stat().st_mode & 0o777) == 0o640
    no_temp_files(tmp_path)
    old = os.umask(0o027)
    try:
        rc, err = dibrgs("export", finished_run, "--ply", tmp_path / "new.ply", "--threads", "1")
    finally:
        os.umask(old)
    assert rc == 0 and ((tmp_path / "new.ply").stat().st_mode & 0o777) == 0o640


def stat_kind(p: Path) -> str:
    import stat

    m = os.lstat(p).st_mode
    return "fifo" if stat.S_ISFIFO(m) else "dir" if stat.S_ISDIR(m) else "file" if stat.S_ISREG(m) else "other"


def test_outputs_are_readable_by_others_under_the_usual_umask(scene24, finished_run, tmp_path):
    """Renders, scenes and run files are created 0o644 under umask 022 (the old writer made every file 0o600)."""
    old = os.umask(0o022)
    try:
        rc, err = dibrgs("render", finished_run, "--cameras", scene24 / "Cams" / "002.txt", "--out",
                         tmp_path / "r", "--threads", "1")
        assert rc == 0, err
        work = copy_run(finished_run, tmp_path / "w")
        rc, err = dibrgs("eval", work, "--threads", "1", "--fps-repeats", "1")
        assert rc == 0, err
    finally:
        os.umask(old)
    for p in [tmp_path / "r" / "002.png", tmp_path / "r" / "002_depth.exr", work / "metrics.json",
              *(work / "renders").glob("*.png")]:
        assert (p.stat().st_mode & 0o777) == 0o644, p


@pytest.mark.slow
def test_corrupt_depth_anything_weights(scene24, tmp_path):
    pytest.importorskip("transformers")
    model = tmp_path / "da"
    model.mkdir()
    (model / "config.json").write_text('{"model_type": "depth_anything"}')
    (model / "model.safetensors").write_bytes(b"garbage" * 100)
    rc, err = dibrgs("init", scene24, "--out", tmp_path / "w", "--depth-model", model, "--threads", "1")
    line = one_line(err)
    assert rc == 2 and str(model) in line and "cannot load the Depth Anything model" in line, err
    assert not (tmp_path / "w" / "init" / "points.ply").exists()


def test_metrics_are_strict_json_when_psnr_is_infinite(tmp_path):
    """A model that renders exactly the held-out images (black, with every Gaussian transparent):
    PSNR is infinite, so metrics.json holds null with the reason, and parses as strict JSON."""
    from dibrgs_core.data.levir import read_scene, write_scene
    from dibrgs_core.data.scene import View
    from train_synth import make_synth_scene

    src = read_scene(make_synth_scene(tmp_path / "src", resolution=16))
    black = write_scene(tmp_path / "black", {k: View(v.camera, np.zeros_like(v.image)) for k, v in src.views.items()})
    work = tmp_path / "w"
    rc, err = dibrgs("train", black, "--out", work, *QUICK, "--iterations", "2", "--method", "3dgs")
    assert rc == 0, err
    st = torch.load(work / MODEL, weights_only=False)
    st["model"]["opacity"] = torch.full_like(st["model"]["opacity"], -60.0)
    torch.save(st, work / MODEL)
    rc, err = dibrgs("eval", work, "--threads", "1", "--fps-repeats", "1")
    assert rc == 0, err
    m = strict_json(work / "metrics.json")
    assert m["psnr"] is None and "infinite" in m["undefined"]["psnr"] and m["ssim"] == pytest.approx(1.0)
    assert all(v["psnr"] is None for v in m["per_view"].values())



# -- what needs another user's rights or another file system ------------------------------------
def _without_root_rights() -> tuple[str, ...]:
    """A command prefix under which file permissions apply (root keeps its uid, loses the override)."""
    if os.geteuid() != 0:
        return ()
    if shutil.which("setpriv") is None:
        pytest.skip("running as root without setpriv: permissions cannot be tested")
    return ("setpriv", "--bounding-set", "-dac_override,-dac_read_search,-fowner")


@pytest.mark.slow
@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_sigterm_before_training_ends_cleanly(tmp_path):
    """SIGTERM (a scheduler's time limit, `timeout`) while the geometry is built from a COLMAP
    scene: pycolmap is loaded then, and its logging library used to answer with a stack dump
    ("*** Aborted at ...", read as a crash) and a kill. Now one line, exit 143, the lock released
    and no temporary or half-written files."""
    from paths import REPO, shared_file

    scene = shared_file("data/brighton_north")
    work = tmp_path / "w"
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.Popen([sys.executable, "-m", "dibrgs_core", "train", str(scene), "--out", str(work),
                          "--preset", "test", "--threads", "1"], stderr=subprocess.PIPE, text=True, env=env,
                         cwd=REPO)
    lines = []
    for line in p.stderr:
        lines.append(line)
        if "geometry initialisation" in line:
            break
    time.sleep(1.0)
    p.send_signal(signal.SIGTERM)
    rest = p.stderr.read()
    p.wait(timeout=120)
    err = "".join(lines) + rest
    assert p.returncode == 143, err[-3000:]
    assert err.strip().splitlines()[-1] == "dibrgs train: terminated (SIGTERM)", err[-3000:]
    assert "Aborted at" not in err and "stack trace" not in err and "Traceback" not in err
    assert not (work / LOCK_NAME).exists()
    assert not (work / "init" / "init_report.json").exists() and not (work / MODEL).exists()
    no_temp_files(work)


def test_a_folder_the_user_cannot_write(scene24, tmp_path):
    locked = tmp_path / "locked"
    locked.mkdir()
    os.chmod(locked, 0o555)
    try:
        r = dibrgs_subprocess("train", scene24, "--out", locked / "run", *QUICK, prefix=_without_root_rights())
        line = one_line(r.stderr)
        assert r.returncode == 1 and str(locked / "run") in line and "permission denied" in line, r.stderr
        assert "choose a folder you can write" in line and not list(locked.iterdir())
        r = dibrgs_subprocess("train", scene24, "--out", locked, *QUICK, prefix=_without_root_rights())
        assert r.returncode == 1 and "permission denied" in one_line(r.stderr)
    finally:
        os.chmod(locked, 0o755)


class _Mount:
    """A tmpfs at ``path`` for the test (root or CAP_SYS_ADMIN needed; skipped with the reason otherwise)."""

    def __init__(self, path: Path, options: str):
        path.mkdir(parents=True, exist_ok=True)
        if shutil.which("mount") is None:
            pytest.skip("no mount command: cannot make a small or read-only file system here")
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True, text=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip() or r.returncode}): needs root or CAP_SYS_ADMIN")
        self.path = path

    def umount(self) -> None:
        subprocess.run(["umount", "-l", str(self.path)], capture_output=True)


@pytest.fixture()
def tmpfs(tmp_path):
    mounts: list[_Mount] = []

    def make(name: str, options: str) -> Path:
        m = _Mount(tmp_path / name, options)
        mounts.append(m)
        return m.path
    yield make
    for m in mounts:
        m.umount()


def test_read_only_file_system(scene24, finished_run, tmp_path, tmpfs):
    ro = tmpfs("ro", "ro,size=1m")
    rc, err = dibrgs("train", scene24, "--out", ro / "run", *QUICK)
    line = one_line(err)
    assert rc == 1 and str(ro / "run") in line and "read-only file system" in line, err
    rc, err = dibrgs("export", finished_run, "--ply", ro / "g.ply", "--threads", "1")
    assert rc == 1 and "read-only file system" in one_line(err) and str(ro / "g.ply") in one_line(err)


def test_disk_full_during_training(scene24, finished_run, tmp_path, tmpfs):
    """A run folder on a 192 KiB file system: the run stops with one line naming the file it could not
    write; no temporary file is left and every file there is whole."""
    small = tmpfs("small", "size=192k")
    work = small / "run"
    for sub in ("init", "pseudo"):  # the caches fit; the checkpoint does not
        shutil.copytree(finished_run / sub, work / sub)
    rc, err = dibrgs("train", scene24, "--out", work, *QUICK, "--iterations", "4")
    line = one_line(err)
    assert rc == 1 and "no space left on the device" in line and str(work) in line, err
    assert "free some space" in line
    no_temp_files(small)
    for p in work.rglob("*.json"):
        strict_json(p)
    assert not (work / MODEL).exists()
    if (work / CHECKPOINT).exists():
        torch.load(work / CHECKPOINT, weights_only=False)


def test_disk_full_during_export(finished_run, tmp_path, tmpfs):
    # A file system with room for half of the export (at least a page), whatever the run's size.
    rc, err = dibrgs("export", finished_run, "--ply", tmp_path / "full.ply", "--threads", "1")
    assert rc == 0, err
    room = max(4096, (tmp_path / "full.ply").stat().st_size // 2 // 4096 * 4096)
    small = tmpfs("small", f"size={room}")
    ply = small / "g.ply"
    ply.write_text("the previous export")
    rc, err = dibrgs("export", finished_run, "--ply", ply, "--threads", "1")
    line = one_line(err)
    assert rc == 1 and f"{ply}: no space left on the device" in line, err
    assert ply.read_text() == "the previous export"
    no_temp_files(small)


# -- kill -9 / SIGINT / SIGTERM: resume to identical parameters ----------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL], ids=["INT", "TERM", "KILL"])
def test_signals_resume_to_identical_parameters(scene24, finished_run, tmp_path, sig):
    """A CLI run stopped by a signal at iteration >= 10 and resumed ends bit-identical to an uninterrupted one."""
    args = ("train", scene24, *QUICK, "--iterations", "40", "--progress-json")
    a = copy_run(finished_run, tmp_path / "a")
    b = copy_run(finished_run, tmp_path / "b")
    rc, err = dibrgs(args[0], args[1], "--out", a, *args[2:])
    assert rc == 0, err
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[2]))
    p = subprocess.Popen([sys.executable, "-m", "dibrgs_core", args[0], str(args[1]), "--out", str(b),
                          *map(str, args[2:])], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    for line in p.stdout:
        if '"iteration"' in line and json.loads(line)["iteration"] >= 10:
            p.send_signal(sig)
            break
    p.wait(timeout=300)
    assert p.returncode == (-9 if sig == signal.SIGKILL else 130), p.stderr.read()[-2000:]
    rc, err = dibrgs(args[0], args[1], "--out", b, *args[2:], "--resume")
    assert rc == 0, err
    pa = torch.load(a / MODEL, weights_only=False)
    pb = torch.load(b / MODEL, weights_only=False)
    for k, v in pa["model"].items():
        assert torch.equal(v, pb["model"][k]), k


def test_corrupt_lpips_backbone(finished_run, tmp_path):
    """LPIPS heads with a damaged torchvision backbone file: one line naming the backbone, no metrics written."""
    heads = {f"lin{k}.model.1.weight": torch.ones(1, c, 1, 1) for k, c in enumerate((64, 128, 256, 512, 512))}
    torch.save(heads, tmp_path / "vgg.pth")
    bb = tmp_path / "vgg16.pth"
    bb.write_bytes(os.urandom(2048))
    work = copy_run(finished_run, tmp_path / "w")
    rc, err = dibrgs("eval", work, "--lpips", tmp_path / "vgg.pth", "--lpips-backbone", bb, "--threads", "1")
    line = one_line(err)
    assert rc == 2 and f"{bb}: not a torch state dict" in line, err
    assert not (work / "metrics.json").exists()


@pytest.mark.slow
def test_no_compiler_is_one_line_naming_the_reference_switch(scene24, finished_run, tmp_path):
    """A machine without a C++ compiler: `dibrgs render` stops with one line saying what is
    missing and naming --rasterizer reference, writes nothing; with that switch it renders."""
    env = {k: v for k, v in os.environ.items() if k not in ("DIBRGS_RASTERIZER", "DIBRGS_EXT_FLAGS")}
    env.update(CXX=str(tmp_path / "no-such-compiler"), DIBRGS_EXT_DIR=str(tmp_path / "ext"))
    work = copy_run(finished_run, tmp_path / "w")
    cams = scene24 / "Cams" / "002.txt"
    r = dibrgs_subprocess("render", work, "--cameras", cams, "--out", tmp_path / "a", env=env)
    line = one_line(r.stderr)
    assert r.returncode != 0 and "no C++ compiler found" in line and "--rasterizer reference" in line, r.stderr
    assert "internal error" not in line and not list((tmp_path / "a").glob("*.png"))
    r = dibrgs_subprocess("render", work, "--cameras", cams, "--out", tmp_path / "b", "--rasterizer", "reference",
                          env=env)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "b" / "002.png").is_file()
