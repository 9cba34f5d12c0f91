"""Resuming a run whose folder was copied or moved: inputs are compared by content, not by path."""
from __future__ import annotations

import json
import shutil

import pytest

from dibrgs_core.common.digest import file_digest
from dibrgs_core.common.errors import InputError
from dibrgs_core.common.report import Report
from dibrgs_core.training.config import TrainConfig
from dibrgs_core.training.run_folder import PSEUDO_PATH_DIGEST, resumed_config


def _checkpoint(cfg: TrainConfig) -> dict:
    return {"config": cfg.to_dict(), "iteration": 4,
            "report": {"values": {PSEUDO_PATH_DIGEST: file_digest(cfg.pseudo_path)}}}


def test_a_moved_pseudo_path_with_the_same_poses_resumes(tmp_path):
    """The add-on writes the path into the run folder; a copied folder names another file with the same
    bytes: safe, and recorded as a resume change. Other poses under any name are refused."""
    old = tmp_path / "a" / "pseudo_path.json"
    old.parent.mkdir()
    old.write_text(json.dumps({"cameras": [[1.0, 2.0]]}))
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

    moved.write_text(json.dumps({"cameras": [[1.0, 2.5]]}))
    with pytest.raises(InputError, match="another configuration than the checkpoint's.*pseudo_path"):
        resumed_config(tmp_path / "b" / "checkpoint.pt", ckpt, TrainConfig(pseudo_path=str(moved)), False, Report())
    # Dropping the path is a change too, whatever its content was.
    with pytest.raises(InputError, match="pseudo_path"):
        resumed_config(tmp_path / "b" / "checkpoint.pt", ckpt, TrainConfig(), False, Report())


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
