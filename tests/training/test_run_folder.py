"""Resuming a run whose folder was copied or moved: inputs are compared by content, not by path."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.camera.serialize import camera_to_dict
from dibrgs_core.common.errors import InputError
from dibrgs_core.common.report import Report
from dibrgs_core.data.levir import write_cams_file
from dibrgs_core.data.load import cameras_digest, read_any_cameras
from dibrgs_core.training.config import TrainConfig
from dibrgs_core.training.run_folder import PSEUDO_PATH_DIGEST, resumed_config


def _checkpoint(cfg: TrainConfig) -> dict:
    return {"config": cfg.to_dict(), "iteration": 4,
            "report": {"values": {PSEUDO_PATH_DIGEST: cameras_digest(read_any_cameras(cfg.pseudo_path))}}}


def _cams(x: float = 0.0) -> list[Camera]:
    K = np.array([[40.0, 0, 20], [0, 40, 20], [0, 0, 1]])
    return [Camera(K=K, w2c=look_at(np.array([x + i, 0.0, 5.0]), np.zeros(3), np.array([0.0, 1.0, 0.0])),
                   width=40, height=40, name=f"p{i}") for i in range(2)]


def test_a_moved_pseudo_path_with_the_same_poses_resumes(tmp_path):
    """The add-on writes the path into the run folder; a copied folder names another file with the same
    cameras: safe, and recorded as a resume change. Other poses under any name are refused."""
    old = tmp_path / "a" / "pseudo_path.json"
    old.parent.mkdir()
    old.write_text(json.dumps([camera_to_dict(c) for c in _cams()]))
    saved = TrainConfig(pseudo_path=str(old))
    ckpt = _checkpoint(saved)
    moved = tmp_path / "b" / "pseudo_path.json"
    moved.parent.mkdir()
    shutil.copy(old, moved)
    old.unlink()  # the original folder may be gone
    rep = Report()
    got = resumed_config(tmp_path / "b" / "checkpoint.pt", ckpt, TrainConfig(pseudo_path=str(moved)), False, rep)
    assert got.pseudo_path == str(moved)
    assert rep.values["resume_changes"] == [["pseudo_path", str(old), str(moved)]]

    moved.write_text(json.dumps([camera_to_dict(c) for c in _cams(0.5)]))
    with pytest.raises(InputError, match="another configuration than the checkpoint's.*pseudo_path"):
        resumed_config(tmp_path / "b" / "checkpoint.pt", ckpt, TrainConfig(pseudo_path=str(moved)), False, Report())
    # Dropping the path is a change too, whatever its content was.
    with pytest.raises(InputError, match="pseudo_path"):
        resumed_config(tmp_path / "b" / "checkpoint.pt", ckpt, TrainConfig(), False, Report())


def test_a_moved_folder_of_path_cameras_resumes(tmp_path):
    """A path given as a folder (LEVIR Cams files) is compared by its cameras too."""
    old = tmp_path / "a"
    old.mkdir()
    for c in _cams():
        write_cams_file(old / f"{c.name}.txt", c)
    ckpt = _checkpoint(TrainConfig(pseudo_path=str(old)))
    moved = tmp_path / "b"
    shutil.copytree(old, moved)
    shutil.rmtree(old)
    got = resumed_config(tmp_path / "w" / "checkpoint.pt", ckpt, TrainConfig(pseudo_path=str(moved)), False, Report())
    assert got.pseudo_path == str(moved)
    write_cams_file(moved / "p1.txt", _cams(0.5)[1])
    with pytest.raises(InputError, match="pseudo_path"):
        resumed_config(tmp_path / "w" / "checkpoint.pt", ckpt, TrainConfig(pseudo_path=str(moved)), False, Report())


@pytest.mark.parametrize("method", ["dibrgs", "3dgs"])
def test_a_setting_the_method_never_reads_does_not_block_a_resume(tmp_path, method):
    """A DIBR-GS run saved before a 3DGS default changed resumes (the change is logged as safe); the
    same change refuses a 3DGS run, whose schedule it is."""
    saved = TrainConfig(method=method)
    saved.gs3d.min_reset_every = 500
    ckpt = {"config": saved.to_dict(), "iteration": 4, "report": {"values": {}}}
    requested = TrainConfig(method=method)
    assert requested.gs3d.min_reset_every != 500
    if method == "dibrgs":
        rep = Report()
        resumed_config(tmp_path / "checkpoint.pt", ckpt, requested, False, rep)
        assert rep.values["resume_changes"] == [["gs3d.min_reset_every", 500, requested.gs3d.min_reset_every]]
        requested.growth.grad_threshold *= 2  # what DIBR-GS reads is still compared
    with pytest.raises(InputError, match="another configuration than the checkpoint's"):
        resumed_config(tmp_path / "checkpoint.pt", ckpt, requested, False, Report())
