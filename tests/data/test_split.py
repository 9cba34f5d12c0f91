"""The split: split.json, --train/--test, the documented defaults, where it came from, and clear errors."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from dibrgs_core.common.errors import InputError
from dibrgs_core.data.load import read_any_scene
from dibrgs_core.data.split import default_split, make_split

from paths import shared_file

LEVIR = [f"{i:03d}" for i in range(21)]
PHOTOS = [f"DJI_{i:04d}" for i in (18, 19, 20, 27, 28, 29, 30, 31, 32)]


def _root(tmp_path: Path, split: dict | str | None = None) -> Path:
    if split is not None:
        (tmp_path / "split.json").write_text(split if isinstance(split, str) else json.dumps(split))
    return tmp_path


def test_defaults_without_split_json(tmp_path):
    """LEVIR-NVS keeps 001/008/015 (000 in neither part); any other scene: 3 evenly spaced views in name order."""
    assert make_split(tmp_path, LEVIR, None) == (["001", "008", "015"], [i for i in LEVIR[1:] if i not in
                                                                          ("001", "008", "015")],
                                                 "default (LEVIR-NVS 3-view protocol)")
    train, test, src = make_split(tmp_path, PHOTOS, None)
    assert train == ["DJI_0018", "DJI_0027", "DJI_0030"] and len(test) == 6 and src.startswith("default (3 evenly")
    assert default_split(PHOTOS)[0] == train


def test_split_json_names_with_or_without_extension(tmp_path):
    root = _root(tmp_path, {"train": ["DJI_0019.png", "DJI_0028.JPG", "DJI_0031"],
                            "test": ["DJI_0018", "DJI_0020.jpeg"]})
    train, test, src = make_split(root, PHOTOS, None)
    assert train == ["DJI_0019", "DJI_0028", "DJI_0031"] and test == ["DJI_0018", "DJI_0020"]
    assert src == str(root / "split.json")


def test_command_line_overrides_each_part(tmp_path):
    root = _root(tmp_path, {"train": ["001", "008", "015"], "test": ["002", "003", "009"]})
    # --train only: the file's test part, less the new training views.
    assert make_split(root, LEVIR, ["9", "2"])[:2] == (["009", "002"], ["003"])
    assert make_split(root, LEVIR, ["9", "2"])[2] == f"--train + {root / 'split.json'}"
    # --test only: the file's training part, less the new test views.
    assert make_split(root, LEVIR, None, ["8", "4"])[:2] == (["001", "015"], ["008", "004"])
    # both: the file is not read at all (not even when broken).
    (root / "split.json").write_text("{broken")
    assert make_split(root, LEVIR, ["1", "2"], ["3"]) == (["001", "002"], ["003"], "--train + --test")


def test_only_train_in_split_json(tmp_path):
    root = _root(tmp_path, {"train": ["001", "011"]})
    train, test, src = make_split(root, LEVIR, None)
    assert train == ["001", "011"] and "000" not in test and len(test) == 18
    assert src == f"{root / 'split.json'} + default (LEVIR-NVS 3-view protocol)"


@pytest.mark.parametrize("content,says", [
    ("{not json", "unreadable split file"),
    ("[]", "expected an object"),
    ('{"train": "001"}', '"train" must be a list'),
    ('{"train": ["001", "nope.png"], "test": ["002"]}', "train: 'nope.png' not in the scene"),
    ('{"train": ["001"], "test": ["999"]}', "test: '999' not in the scene"),
    ('{"train": ["001", "002"], "test": ["002"]}', "in both the training and the test set"),
    ('{"train": [], "test": ["002"]}', "no training view"),
])
def test_bad_split_json(tmp_path, content, says):
    root = _root(tmp_path, content)
    with pytest.raises(InputError, match=says.replace("(", r"\(").replace("[", r"\[")) as e:
        make_split(root, LEVIR, None)
    assert e.value.path in (root / "split.json", root)


def test_split_json_that_is_a_folder(tmp_path):
    (tmp_path / "split.json").mkdir()
    with pytest.raises(InputError, match="is not a file") as e:
        make_split(tmp_path, LEVIR, None)
    assert e.value.path == tmp_path / "split.json"


def test_train_all_holds_out_only_what_test_names(tmp_path):
    """``--train all``: every view trains, split.json's test part included; with --test, all but those."""
    root = _root(tmp_path, {"train": ["001"], "test": ["002", "003"]})
    assert make_split(root, LEVIR, ["all"]) == (LEVIR, [], "--train all")
    assert make_split(root, PHOTOS, ["ALL"], ["DJI_0020.png"]) == (
        [i for i in PHOTOS if i != "DJI_0020"], ["DJI_0020"], "--train all + --test")
    # A scene with a view named "all": the name wins.
    assert make_split(tmp_path / "none", ["all", "b", "c"], ["all"])[:2] == (["all"], ["b", "c"])
    with pytest.raises(InputError, match="--train: 'all' not in the scene"):
        make_split(tmp_path, PHOTOS, ["all", "DJI_0019"])


def test_test_none_holds_nothing_out(tmp_path):
    """``--test none``: the training part as given (or split.json's), nothing held out, the other views left out."""
    root = _root(tmp_path, {"train": ["001"], "test": ["002", "003"]})
    assert make_split(root, LEVIR, ["001", "005"], ["none"]) == (["001", "005"], [], "--train + --test")
    assert make_split(root, LEVIR, None, ["None"])[:2] == (["001"], [])
    assert make_split(tmp_path / "v", ["none", "b", "c"], ["b"], ["none"])[:2] == (["b"], ["none"])  # a view's name wins
    with pytest.raises(InputError, match="--test: 'none' not in the scene"):
        make_split(root, LEVIR, ["001"], ["none", "002"])


def test_bad_command_line_names(tmp_path):
    with pytest.raises(InputError, match=r"--train: 'DJI_9999' not in the scene \(its views: DJI_0018") as e:
        make_split(tmp_path, PHOTOS, ["DJI_0019", "DJI_9999"])
    assert e.value.path is None
    with pytest.raises(InputError, match="in both"):
        make_split(tmp_path, LEVIR, ["1", "2"], ["2"])


def test_brighton_north_uses_its_split_json(tmp_path):
    """The real scene's split.json: train on the middle photo of each strip, test on the other six."""
    root = shared_file("data/brighton_north")
    s = read_any_scene(root)
    assert s.train == ["DJI_0019", "DJI_0028", "DJI_0031"] and len(s.test) == 6
    assert s.split_source == str(root / "split.json")
    s2 = read_any_scene(root, train_ids=["DJI_0019.png", "DJI_0031"])
    assert s2.train == ["DJI_0019", "DJI_0031"] and "DJI_0028" not in s2.test and len(s2.test) == 6
    # A copy without split.json gets the documented default, not the file's split.
    copy = tmp_path / "bn"
    shutil.copytree(root, copy, ignore=shutil.ignore_patterns("split.json", "images"))
    (copy / "images").symlink_to(root / "images")
    assert read_any_scene(copy).train == ["DJI_0018", "DJI_0027", "DJI_0030"]
    # `dibrgs info` names the training cameras' trajectory: one line across the three strips.
    from dibrgs_core.commands.info import summarize

    info = summarize(s)
    assert info["trajectory"]["kind"] == "strips" and "orbit" not in info
    assert info["trajectory"]["lines"] == [["DJI_0019", "DJI_0028", "DJI_0031"]]
