"""The split reaches training and evaluation: split.json with 10 training views skips pseudo views (auto),
report.json / config.json / the log say where the split came from, eval uses the run's own split and
refuses a scene that changed since training."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch

from run_synth import QUICK, dibrgs

torch.set_num_threads(1)


def test_ten_training_views_from_split_json_skip_pseudo_views(scene24, tmp_path, caplog):
    """`auto` pseudo views are skipped with >= 10 training views: reachable through split.json, end to end."""
    scene = Path(shutil.copytree(scene24, tmp_path / "scene"))
    train = [f"{i:03d}.png" for i in range(1, 11)]
    (scene / "split.json").write_text(json.dumps({"train": train, "test": ["011", "015", "020"]}))
    work = tmp_path / "w"
    with caplog.at_level("INFO", logger="dibrgs"):
        rc, err = dibrgs("train", scene, "--out", work, *QUICK, "--iterations", "3")
    assert rc == 0, err
    rep = json.loads((work / "report.json").read_text())
    d = {x["step"]: x for x in rep["decisions"]}
    assert d["pseudo_views"]["applied"] is False
    assert d["pseudo_views"]["reason"] == "10 training views are dense enough (>= 10)"
    assert not (work / "pseudo").exists()
    sc = rep["values"]["scene"]
    assert sc["train"] == [f"{i:03d}" for i in range(1, 11)] and sc["test"] == ["011", "015", "020"]
    assert sc["split_source"] == str(scene / "split.json")
    cfg = json.loads((work / "config.json").read_text())
    assert cfg["run"]["split_source"] == str(scene / "split.json") and len(cfg["run"]["train"]) == 10
    assert f"split from {scene / 'split.json'}" in caplog.text
    # The init was made from the ten views.
    assert json.loads((work / "init" / "init_report.json").read_text())["values"]["train"] == sc["train"]


def test_eval_uses_the_runs_split_and_refuses_a_changed_scene(scene24, tmp_path):
    scene = Path(shutil.copytree(scene24, tmp_path / "scene"))
    work = tmp_path / "w"
    rc, err = dibrgs("train", scene, "--out", work, *QUICK, "--iterations", "2", "--no-pseudo",
                     "--train", "1,8,15", "--test", "2,3")
    assert rc == 0, err
    rc, err = dibrgs("eval", work, "--threads", "1", "--fps-repeats", "1")
    assert rc == 0, err
    m = json.loads((work / "metrics.json").read_text())
    assert m["views"] == 2 and sorted(m["per_view"]) == ["002", "003"]
    assert m["split"]["test"] == ["002", "003"] and "the run" in m["split"]["source"]
    assert sorted(p.stem for p in (work / "renders").glob("*.png")) == ["002", "003"]
    # The scene was edited after training: evaluating against it would mix two scenes.
    from dibrgs_core.data.images import read_image, write_png

    img = read_image(scene / "Images" / "002.png")
    write_png(scene / "Images" / "002.png", 1.0 - img)
    rc, err = dibrgs("eval", work, "--threads", "1", "--fps-repeats", "1")
    lines = [x for x in err.splitlines() if ": error: " in x]
    assert rc == 2 and len(lines) == 1 and "the scene changed since" in lines[0] and "train again" in lines[0]


def test_library_split_is_recorded(scene24, finished_run, tmp_path):
    """The Trainer takes the split too (what the CLI's --train/--test pass), and resume keeps to it."""
    from dibrgs_core.training.config import preset
    from dibrgs_core.training.trainer import Trainer

    cfg = preset("test")
    cfg.iterations = 2
    cfg.pseudo.mode = "off"
    work = tmp_path / "w"
    tr = Trainer(scene24, work, cfg, train_ids=["001", "008"], test_ids=["002"])
    assert tr.run().status == "done"
    values = json.loads((work / "report.json").read_text())["values"]["scene"]
    assert values["train"] == ["001", "008"] and values["split_source"] == "--train + --test"
    assert values["layout"] == "levir"  # which reader read the folder
    cfg.iterations = 3
    from dibrgs_core.common.errors import InputError

    with pytest.raises(InputError, match="another split"):
        Trainer(scene24, work, cfg, resume=True).run()
    assert Trainer(scene24, work, cfg, resume=True, train_ids=["001", "008"], test_ids=["002"]).run().iteration == 3
