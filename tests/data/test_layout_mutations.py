"""Every reader of a photogrammetry tool's camera file, and of the JSON camera lists `render
--cameras` and `--pseudo-path` take, given that file with one thing changed at random (a key or
element removed, a value replaced by null, a string, a list, NaN, infinity, a huge number, broken
markup), gives cameras or an InputError naming the file: never another exception (fixed seeds;
these mutations found a division by zero and seven type or overflow errors in the readers)."""
from __future__ import annotations

import copy
import json
import random
import re
from pathlib import Path

import pytest

from dibrgs_core.common.errors import InputError
from dibrgs_core.data.frame_layouts import layout_frames
from dibrgs_core.data.load import read_any_cameras

pytest.importorskip("pycolmap")

import photo_synth  # noqa: E402

# robustness sweeps: the full suite runs them, the quick tier does not
pytestmark = pytest.mark.slow
MUTATIONS = 120
_VALUES = [None, "", "x", -1, 0, 1.5, True, [], {}, [1], "nan", float("inf"), 10**30, [None, None, None]]
_TOKENS = ["nan", "inf", "", "x", "0", "-1", "1e309", "<", "\"", "1 2", "\n"]
_TOKEN = re.compile(r"-?\d+(\.\d+)?(e-?\d+)?|<[^<>]*>|\"[^\"]*\"|\w+")


def _json_mutation(data: object, rng: random.Random) -> object:
    """``data`` with one node removed or replaced."""
    d = copy.deepcopy(data)
    paths, stack = [], [((), d)]
    while stack:
        path, node = stack.pop()
        if path:
            paths.append(path)
        items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
        stack.extend((path + (k,), v) for k, v in items)
    path = rng.choice(paths)
    parent = d
    for k in path[:-1]:
        parent = parent[k]
    if rng.random() < 0.35:
        del parent[path[-1]]
    else:
        parent[path[-1]] = rng.choice(_VALUES)
    return d


def _text_mutation(text: str, rng: random.Random) -> str:
    """``text`` with one number, tag, quoted string or word removed, replaced or doubled."""
    m = rng.choice(list(_TOKEN.finditer(text)))
    op = rng.random()
    new = "" if op < 0.3 else rng.choice(_TOKENS) if op < 0.8 else m.group(0) * 2
    return text[:m.start()] + new + text[m.end():]


def _files(layout: str, levir: Path, out: Path) -> list[Path]:
    """Write the generated scene in ``layout``; its camera files."""
    if layout == "meshroom":
        return [photo_synth.levir_as_meshroom(levir, out)]
    if layout == "openmvg":
        return [photo_synth.levir_as_openmvg(levir, out)]
    if layout == "opensfm":
        photo_synth.levir_as_opensfm(levir, out)
        return [out / "opensfm" / "reconstruction.json"]
    if layout == "transforms":
        photo_synth.levir_as_transforms(levir, out)
        return [out / "transforms.json"]
    if layout == "metashape":
        photo_synth.levir_as_metashape(levir, out)
        return [out / "cameras.xml"]
    if layout == "realitycapture":
        photo_synth.levir_as_realitycapture(levir, out)
        return sorted((out / "images").glob("*.xmp"))[:3]
    if layout == "camera_list":
        from dibrgs_core.camera.serialize import camera_to_dict
        from dibrgs_core.data.load import read_any_scene

        out.mkdir()
        cams = [camera_to_dict(c) for c in read_any_scene(levir, load_depth=False).cameras[:4]]
        (out / "cams.json").write_text(json.dumps({"cameras": [{**c, "depth_range": [1.0, 500.0]} for c in cams]}))
        return [out / "cams.json"]
    photo_synth.levir_as_bundler(levir, out)
    return sorted(p for p in out.rglob("*") if p.suffix in (".out", ".txt") and p.is_file())


@pytest.mark.parametrize("layout", ["meshroom", "openmvg", "opensfm", "transforms", "metashape", "realitycapture",
                                    "bundler", "camera_list"])
def test_a_changed_camera_file_reads_or_is_named(tiny_scene, tmp_path, layout):
    out = tmp_path / layout
    files = _files(layout, tiny_scene, out)
    texts = {f: f.read_text() for f in files}
    rng = random.Random(layout)
    outcomes = {"read": 0, "refused": 0}
    for _ in range(MUTATIONS):
        f = rng.choice(files)
        if f.suffix == ".json" or f.suffix == ".sfm":
            f.write_text(json.dumps(_json_mutation(json.loads(texts[f]), rng)))
        else:
            f.write_text(_text_mutation(texts[f], rng))
        try:
            read_any_cameras(f) if layout == "camera_list" else layout_frames(out)
            outcomes["read"] += 1
        except InputError as e:
            assert str(e).strip() and "\n" not in str(e).strip(), e  # one line
            outcomes["refused"] += 1
        f.write_text(texts[f])
    assert outcomes["refused"] > 0 and outcomes["read"] > 0, outcomes  # the mutations reach both outcomes
