"""SfM with known poses (real pycolmap) on ray-cast synthetic scenes."""
from __future__ import annotations

import numpy as np
import pytest
from geom_synth import make_synthetic_scene
from threads import torch_threads

from dibrgs_core.geometry.sfm import SparseCloud, triangulate_known_poses


def _depth_errors(scene, pts):
    errs = []
    for v in scene.train_views():
        uv, z = v.camera.project(pts)
        u, w = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (u < v.camera.width) & (w >= 0) & (w < v.camera.height)
        errs.append(np.abs(v.depth[w[ok], u[ok]] - z[ok]) / z[ok])
    return np.concatenate(errs)


@pytest.mark.stability
@pytest.mark.parametrize("offset", [pytest.param((0.0, 0.0, 0.0), marks=pytest.mark.slow), (1.2e5, -3.4e5, 250.0)])
def test_triangulation_matches_true_depth(offset):
    """SfM with fixed poses at normal and ~1e5 coordinates: triangulated depth within 1% of truth."""
    scene, _ = make_synthetic_scene(128, offset=offset, up=(0.2, -0.1, 1.0))
    vs = scene.train_views()
    sc = triangulate_known_poses([v.camera for v in vs], [v.image for v in vs])
    assert len(sc) >= 50
    assert np.isfinite(sc.points).all()
    assert sc.colors.dtype == np.uint8 and sc.colors.shape == sc.points.shape
    assert (sc.track_lengths >= 2).all() and (sc.track_lengths <= 3).all()
    # Poses are held fixed, so points land on the true surface (within 1% of depth for most).
    rel = _depth_errors(scene, sc.points)
    assert np.median(rel) < 0.005
    assert np.mean(rel < 0.01) > 0.85


@pytest.mark.stability
@pytest.mark.slow
def test_textureless_views_give_empty_cloud():
    """Textureless views: SfM returns an empty cloud instead of failing."""
    scene, _ = make_synthetic_scene(64)
    vs = scene.train_views()
    blank = [np.full_like(v.image, 0.5) for v in vs]
    sc = triangulate_known_poses([v.camera for v in vs], blank)
    assert isinstance(sc, SparseCloud) and len(sc) == 0
    assert sc.points.shape == (0, 3)


@pytest.mark.stability
def test_triangulation_does_not_depend_on_units():
    """The same mapping strip in units x0.001 and x1000 triangulates the same points (scaled): COLMAP's
    solvers have absolute tolerances, so coordinates go in at the cameras' own spread (at x0.001 the
    points used to move by 0.3 % of the scene)."""
    from geom_synth import make_grid_scene, scaled_scene

    base, _ = make_grid_scene(96, seed=3)
    clouds = {}
    for f in (1e-3, 1.0, 1e3):
        vs = scaled_scene(base, f).train_views()
        clouds[f] = triangulate_known_poses([v.camera for v in vs], [v.image for v in vs])
    ref = clouds[1.0].points
    assert len(ref) >= 50
    for f in (1e-3, 1e3):
        assert len(clouds[f]) == len(ref)
        assert np.abs(clouds[f].points / f - ref).max() < 1e-6 * 110  # the strip flies 110 units high


@pytest.mark.slow
def test_triangulation_is_the_same_every_time():
    """The same views give the same points on every run (the geometry caches and the units test
    rely on it): on two threads COLMAP gave 56, 68, 75 or 97 points for these views,
    about one run in twelve (so sixteen runs, to catch it more often than not)."""
    from geom_synth import make_grid_scene

    base, _ = make_grid_scene(96, seed=3)
    vs = base.train_views()
    runs = [triangulate_known_poses([v.camera for v in vs], [v.image for v in vs]) for _ in range(16)]
    for r in runs[1:]:
        assert len(r) == len(runs[0]) and np.array_equal(r.points, runs[0].points)


def test_colmap_progress_lines_only_when_debugging(capfd):
    """COLMAP writes some sixty INFO lines a reconstruction straight to stderr; they show only when
    the package logs at DEBUG (`dibrgs -v`), and COLMAP's own level is left as it was."""
    import logging

    import pycolmap

    scene, _ = make_synthetic_scene(64)
    vs = scene.train_views()
    logger = logging.getLogger("dibrgs.sfm")
    old_level = logger.level
    before = pycolmap.logging.minloglevel
    try:
        logger.setLevel(logging.INFO)
        capfd.readouterr()
        quiet = triangulate_known_poses([v.camera for v in vs], [v.image for v in vs])
        quiet_err = capfd.readouterr().err
        assert pycolmap.logging.minloglevel == before
        logger.setLevel(logging.DEBUG)
        loud = triangulate_known_poses([v.camera for v in vs], [v.image for v in vs])
        loud_err = capfd.readouterr().err
    finally:
        logger.setLevel(old_level)
    assert pycolmap.logging.minloglevel == before
    assert "feature_extraction" not in quiet_err and "Feature extraction" not in quiet_err
    assert "Feature extraction" in loud_err
    np.testing.assert_array_equal(quiet.points, loud.points)


def test_neighbour_pairs_of_a_long_strip():
    """Each photo is matched with its nearest; few photos: every pair (None)."""
    from dibrgs_core.geometry.sfm import neighbour_pairs
    from geom_synth import nadir

    cams = [nadir(20.0 * i) for i in range(30)]
    pairs = neighbour_pairs(cams, 4)
    assert all(0 < j - i <= 4 for i, j in pairs)  # the nearest (four on one side at the ends)
    assert {(i, i + d) for i in range(30) for d in (1, 2) if i + d < 30} <= set(pairs)
    assert len(set(pairs)) == len(pairs) < 30 * 4 // 2 + 6
    assert neighbour_pairs(cams[:5], 4) is None and neighbour_pairs(cams, 0) is None


@pytest.mark.slow
def test_a_strip_matched_with_neighbours_triangulates_as_every_pair():
    """Twelve photos in a strip matched with their 4 nearest (30 of 66 pairs): about as many points,
    as close to the surface, as matching every pair."""
    from dibrgs_core.geometry.config import SfmConfig
    from geom_synth import make_grid_scene

    scene, _ = make_grid_scene(96, n_views=12, spacing=20.0, seed=5)
    vs = scene.train_views()
    cams, imgs = [v.camera for v in vs], [v.image for v in vs]
    near = triangulate_known_poses(cams, imgs, config=SfmConfig(max_neighbours=4))
    every = triangulate_known_poses(cams, imgs, config=SfmConfig(max_neighbours=0))
    assert len(near) >= 0.8 * len(every) and len(every) >= 50, (len(near), len(every))
    assert np.median(_depth_errors(scene, near.points)) < 0.005


def test_photos_extracted_on_several_threads_triangulate_as_on_one():
    """SIFT shares the photos out over torch's thread count; COLMAP numbers them as they finish, and
    they are renumbered in name order, so the points are those of one thread to the bit."""
    from geom_synth import make_grid_scene

    base, _ = make_grid_scene(96, seed=3)
    vs = base.train_views()
    clouds = {}
    for n in (1, 2, 3):
        with torch_threads(n):
            clouds[n] = triangulate_known_poses([v.camera for v in vs], [v.image for v in vs])
    assert len(clouds[1]) >= 50
    for n in (2, 3):
        assert np.array_equal(clouds[n].points, clouds[1].points) and np.array_equal(clouds[n].colors, clouds[1].colors)


def test_a_database_numbered_out_of_order_is_renumbered_by_name(tmp_path):
    """Features extracted in reverse name order (ids 3, 2, 1 for a, b, c) come out with ids 1, 2, 3,
    each image with its own keypoints, descriptors, camera and frame."""
    import pycolmap
    from PIL import Image

    from dibrgs_core.data.images import to_uint8
    from dibrgs_core.geometry.sfm import _number_in_order
    from geom_synth import make_grid_scene

    base, _ = make_grid_scene(96, seed=3)
    (tmp_path / "img").mkdir()
    names = ["a.png", "b.png", "c.png"]
    for name, v in zip(names, base.train_views()):
        Image.fromarray(to_uint8(v.image)).save(tmp_path / "img" / name)
    db_path = tmp_path / "db.db"
    eo = pycolmap.FeatureExtractionOptions()
    eo.num_threads = 1
    for name in reversed(names):
        pycolmap.extract_features(db_path, tmp_path / "img", image_names=[name], camera_mode=pycolmap.CameraMode.SINGLE,
                                  extraction_options=eo, device=pycolmap.Device.cpu)

    def state():
        db = pycolmap.Database.open(db_path)
        try:
            frames = {f.frame_id: f for f in db.read_all_frames()}
            return {im.name: (im.image_id, im.camera_id, db.read_keypoints(im.image_id).copy(),
                              np.asarray(db.read_descriptors(im.image_id).data).copy(),
                              [(d.sensor_id.id, d.id) for d in frames[im.frame_id].data_ids])
                    for im in db.read_all_images()}
        finally:
            db.close()

    before = state()
    assert [before[n][0] for n in names] == [3, 2, 1]
    _number_in_order(pycolmap, db_path)
    after = state()
    assert [after[n][0] for n in names] == [1, 2, 3]
    for n in names:
        image_id, camera_id, kp, desc, data_ids = after[n]
        assert camera_id == before[n][1] and data_ids == [(camera_id, image_id)]
        assert np.array_equal(kp, before[n][2]) and np.array_equal(desc, before[n][3]) and len(kp) > 0


def test_no_features_where_a_photo_holds_no_data(tmp_path):
    """A photo whose left half holds no data gets keypoints only in its right half, 4 px in from the
    edge of the data (the masks go with every photo of the one extraction; the others' are whole)."""
    import pycolmap
    from geom_synth import make_grid_scene

    from dibrgs_core.geometry.sfm import MASK_MARGIN_PX

    base, _ = make_grid_scene(96, seed=3)
    vs = base.train_views()
    W = vs[0].camera.width
    valid = np.ones(vs[0].image.shape[:2], bool)
    valid[:, : W // 2] = False
    cloud = triangulate_known_poses([v.camera for v in vs], [v.image for v in vs], work_dir=tmp_path / "sfm",
                                    valid=[valid, None, None])
    assert len(cloud) > 0
    db = pycolmap.Database.open(tmp_path / "sfm" / "database.db")
    try:
        xs = {im.name: db.read_keypoints(im.image_id)[:, 0] for im in db.read_all_images()}
    finally:
        db.close()
    assert len(xs["0000.png"]) > 0 and xs["0000.png"].min() >= W // 2 + MASK_MARGIN_PX - 1
    assert min(xs["0001.png"].min(), xs["0002.png"].min()) < W // 2  # the others are not masked
