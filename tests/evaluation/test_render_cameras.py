"""``dibrgs render --cameras``: cameras from a COLMAP model as well as LEVIR Cams files."""
from __future__ import annotations

import shutil

import numpy as np

from dibrgs_core.data.colmap import write_colmap_model
from dibrgs_core.data.images import read_image
from dibrgs_core.data.levir import read_cameras
from dibrgs_core.data.load import read_any_cameras
from run_synth import dibrgs


def test_a_colmap_model_renders_as_the_same_cameras_in_cams_files(scene24, finished_run, tmp_path):
    cams = read_cameras(scene24 / "Cams")[:3]
    # A COLMAP scene folder as users have them: the model under sparse/0, and other text files
    # (reference points, notes) beside it that are no cameras.
    root = tmp_path / "colmap_scene"
    write_colmap_model(cams, root / "sparse" / "0", binary=False)
    (root / "reference_points.txt").write_text("# x y z\n0 0 0\n")
    got = read_any_cameras(root)
    assert [c.name for c in got] == [c.name for c in cams]
    for a, b in zip(got, cams):
        assert (a.width, a.height) == (b.width, b.height)
        np.testing.assert_allclose(a.K, b.K, atol=1e-9)
        np.testing.assert_allclose(a.w2c, b.w2c, atol=1e-9)
    assert len(read_any_cameras(root / "sparse" / "0")) == 3  # the model's own folder too
    levir = tmp_path / "cams"
    levir.mkdir()
    for c in cams:
        shutil.copy(scene24 / "Cams" / f"{c.name}.txt", levir)
    for src, out in ((root, tmp_path / "from_colmap"), (levir, tmp_path / "from_cams")):
        rc, err = dibrgs("render", finished_run, "--cameras", src, "--out", out, "--threads", "1")
        assert rc == 0, err
    for c in cams:
        a = read_image(tmp_path / "from_colmap" / f"{c.name}.png")
        b = read_image(tmp_path / "from_cams" / f"{c.name}.png")
        assert a.shape == (c.height, c.width, 3) and np.abs(a - b).max() <= 1.5 / 255
        assert a.std() > 0.01  # the scene, not a blank image
    # A folder that holds neither is still one clear line.
    empty = tmp_path / "empty"
    empty.mkdir()
    rc, err = dibrgs("render", finished_run, "--cameras", empty, "--out", tmp_path / "none", "--threads", "1")
    assert rc == 2 and "empty" in err and len(err.strip().splitlines()) == 1
