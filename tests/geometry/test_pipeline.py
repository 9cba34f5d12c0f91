"""initialise(): end to end on synthetic scenes and the stiff cases; the CLI on tiny_scene."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from geom_synth import make_synthetic_scene, save_tiny_depth_anything

from dibrgs_core.data.ply import read_ply
from dibrgs_core.geometry.config import InitConfig
from dibrgs_core.geometry.height_map import HeightMap
from dibrgs_core.geometry.pipeline import initialise
from dibrgs_core.geometry.pointcloud import zbuffer

torch.set_num_threads(2)


def _decisions(out):
    rep = json.loads((out / "init_report.json").read_text())
    return {d["step"]: d for d in rep["decisions"]}, rep["values"]


def _mae(scene, pts):
    errs = []
    for v in scene.train_views():
        d = zbuffer(v.camera, pts)
        ok = np.isfinite(d)
        errs.append(np.abs(d[ok] - v.depth[ok]) / v.depth[ok])
    return float(np.mean(np.concatenate(errs)))


@pytest.mark.stability
@pytest.mark.slow
@pytest.mark.parametrize("offset", [(0.0, 0.0, 0.0), (2.5e5, 4.1e6, 120.0)])
def test_initialise_mvs_end_to_end(tmp_path, offset):
    """Whole geometry stage at normal and georeferenced (~1e5..4e6) coordinates: finite cloud within 5% of true depth."""
    scene, _ = make_synthetic_scene(96, offset=offset, up=(0.1, 0.3, 1.0))
    res = initialise(scene, tmp_path, InitConfig(depth_prior="mvs"))
    dec, vals = _decisions(tmp_path)
    assert dec["sfm"]["applied"] and dec["depth_prior"]["applied"] and dec["overlap_removal"]["applied"]
    assert dec["height_map"]["applied"] and not dec["align"]["applied"]  # metric prior: fit kept as a check
    fits = vals["alignment"]
    assert all(abs(f["a"] - 1) < 0.1 for f in fits if f["method"] == "robust-lsq")
    assert np.isfinite(res.points).all() and len(res.points) > 1000
    assert _mae(scene, res.points) < 0.05  # reprojected cloud within 5% of true depth on average
    P, C = read_ply(tmp_path / "points.ply")
    assert np.allclose(P, res.points, atol=1e-6) and (C == res.colors).all()
    hm = HeightMap.load(tmp_path / "height_map.npz")
    assert np.isfinite(hm.bounds).all() and hm.allows(res.points).mean() > 0.95
    # A point far above the scene (a floater near the cameras) is refused.
    cam = scene.train_views()[0].camera
    assert not hm.allows(cam.center[None] + 0.0)[0]


def test_large_photos_are_worked_on_at_the_working_size(tmp_path):
    """Training photos longer than ``max_side`` are area-averaged down with their cameras (a drone's
    8-20 MP photos back-projected at full size took 16 GB): the stage says so, works on a quarter
    of the pixels, and its cloud is as close to the true surface; photos within it are untouched."""
    scene, _ = make_synthetic_scene(128)
    full = initialise(scene, tmp_path / "full", InitConfig(depth_prior="gt", max_side=0))
    small = initialise(scene, tmp_path / "small", InitConfig(depth_prior="gt", max_side=64))
    dec_full, _ = _decisions(tmp_path / "full")
    dec, _ = _decisions(tmp_path / "small")
    assert not dec_full["working_size"]["applied"]
    assert dec["working_size"]["applied"] and "64x64" in dec["working_size"]["reason"]
    assert len(small.dense_points) < 0.3 * len(full.dense_points)
    assert _mae(scene, small.points) < 0.02 and _mae(scene, full.points) < 0.02
    kept = initialise(scene, tmp_path / "kept", InitConfig(depth_prior="gt", max_side=128))
    assert not _decisions(tmp_path / "kept")[0]["working_size"]["applied"]
    assert len(kept.dense_points) == len(full.dense_points)


@pytest.mark.stability
@pytest.mark.slow
def test_gt_prior_oracle_and_no_sfm_points(tmp_path):
    """Blank images: SfM finds nothing, MVS nothing; the gt prior still gives a cloud, with reasons logged."""
    scene, _ = make_synthetic_scene(48)
    for v in scene.views.values():
        v.image[:] = 0.5
    res = initialise(scene, tmp_path, InitConfig(depth_prior="gt"))
    dec, vals = _decisions(tmp_path)
    assert not dec["sfm"]["applied"] and "< 20" in dec["sfm"]["reason"]
    assert vals["sfm_points"] == 0
    assert all(f["n_points"] == 0 for f in vals["alignment"])
    assert len(res.points) > 100 and np.isfinite(res.points).all()
    assert _mae(scene, res.points) < 0.02
    # And with the weight-free prior nothing matches at all: the plane fallback keeps the run going.
    res = initialise(scene, tmp_path / "mvs", InitConfig(depth_prior="mvs"))
    dec, _ = _decisions(tmp_path / "mvs")
    assert dec["plane_fallback"]["applied"] and np.isfinite(res.points).all() and len(res.points) > 0


@pytest.mark.stability
@pytest.mark.slow
def test_gt_with_nan_and_zero_depths(tmp_path):
    """Depth prior with NaN and zero pixels: they are dropped, the cloud stays finite."""
    scene, _ = make_synthetic_scene(48)
    for v in scene.views.values():
        v.depth[::3] = np.nan
        v.depth[1::5] = 0.0
    res = initialise(scene, tmp_path, InitConfig(depth_prior="gt"))
    assert np.isfinite(res.points).all() and len(res.points) > 100


@pytest.mark.slow
@pytest.mark.stability
def test_horizontal_cameras_skip_overlap_and_height_map(tmp_path):
    """Cameras looking horizontally: overlap removal and height map are skipped with a reason in the report."""
    scene, _ = make_synthetic_scene(48, horizontal=True)
    res = initialise(scene, tmp_path, InitConfig(depth_prior="gt"))
    dec, _ = _decisions(tmp_path)
    assert not dec["overlap_removal"]["applied"] and not dec["height_map"]["applied"]
    assert "ambiguous" in dec["height_map"]["reason"] or "near-nadir" in dec["height_map"]["reason"]
    assert res.height_map is None and not (tmp_path / "height_map.npz").exists()
    assert np.isfinite(res.points).all()


@pytest.mark.slow
def test_a_depth_anything_prior_goes_through_the_alignment(tmp_path):
    """The learnt prior's path through the stage: ``auto`` with ``--depth-model`` picks Depth
    Anything (a tiny random model saved and loaded as a local download), whose relative disparity
    is fitted per view to the SfM depths by robust least squares; the fits and the decision are in
    the report and the cloud is finite. (Random weights predict no shape, so the fit is near a
    constant depth at the scene's distance: this checks the path, not the model.)"""
    scene, _ = make_synthetic_scene(96)
    model = save_tiny_depth_anything(tmp_path / "depth_anything")
    res = initialise(scene, tmp_path / "w", InitConfig(depth_model=str(model)))
    dec, vals = _decisions(tmp_path / "w")
    assert vals["prior"] == "depth-anything-v2" and dec["depth_prior"]["applied"]
    assert dec["align"]["applied"] and "robust least squares against SfM depths" in dec["align"]["reason"]
    fits = vals["alignment"]
    assert len(fits) == len(scene.train_views()) and all(f["method"] == "robust-lsq" and f["n_points"] > 0
                                                         for f in fits)
    assert all(np.isfinite([f["a"], f["b"]]).all() for f in fits)
    assert len(res.points) > 1000 and np.isfinite(res.points).all()
    # Fitted to the SfM depths: the cloud lies at the scene's distance, whatever the model predicted.
    d = zbuffer(scene.train_views()[0].camera, res.points)
    assert 0.7 < np.nanmedian(d) / vals["ref_distance"] < 1.4


def test_dense_sfm_skips_prior(tmp_path):
    scene, _ = make_synthetic_scene(128)
    res = initialise(scene, tmp_path, InitConfig(depth_prior="mvs", dense_sfm_ratio=1e-3))
    dec, vals = _decisions(tmp_path)
    assert not dec["depth_prior"]["applied"] and "already dense" in dec["depth_prior"]["reason"]
    assert len(res.points) == vals["sfm_points"]


def test_cli_on_tiny_scene(tiny_scene, tmp_path):
    from dibrgs_core.cli import main

    rc = main(["init", str(tiny_scene), "--out", str(tmp_path / "work")])
    assert rc == 0
    out = tmp_path / "work" / "init"
    P, _ = read_ply(out / "points.ply")
    assert len(P) > 0 and np.isfinite(P).all()
    dec, vals = _decisions(out)
    assert {"sfm", "depth_prior", "height_map"} <= set(dec)
    assert vals["prior"] == "mvs"
    # The depth-anything prior without weights fails at once, naming the option.
    rc = main(["init", str(tiny_scene), "--out", str(tmp_path / "w2"), "--depth-prior", "depth-anything-v2",
               "--depth-model", "depth-anything/Depth-Anything-V2-Small-hf"])
    assert rc == 2


@pytest.fixture(scope="module")
def grid_scene():
    """A 96x96 nadir strip whose cameras' axes meet 259 units below the ground (no depth ranges)."""
    from geom_synth import make_grid_scene

    return make_grid_scene(96, seed=3)[0]


def _relative_figures(scene, res):
    """Scale-free figures of a geometry result: dense coverage and Abs Rel (all / measured), point counts."""
    from dibrgs_core.geometry.pointcloud import zbuffer

    out = {"points": len(res.points), "completed": int((res.confidence < 0.5).sum())}
    for name, keep in (("all", np.ones(len(res.dense_points), bool)), ("measured", res.dense_confidence >= 0.5)):
        cov, rel = [], []
        for v in scene.train_views():
            d = zbuffer(v.camera, res.dense_points[keep])
            ok = np.isfinite(d)
            cov.append(ok.mean())
            rel.append(np.abs(d[ok] - v.depth[ok]) / v.depth[ok])
        out[f"cov_{name}"] = float(np.mean(cov))
        out[f"absrel_{name}"] = float(np.mean(np.concatenate(rel)))
    return out


def test_mapping_grid_scale_completion_and_confidence(grid_scene, tmp_path):
    """Parallel nadir cameras: the scene's scale comes from the SfM depths (not the meaningless look-at
    point), unmatched pixels are completed from a height field at confidence < 0.5, and the confidence
    reaches points.ply."""
    from dibrgs_core.data.ply import read_ply_confidence

    res = initialise(grid_scene, tmp_path, InitConfig(depth_prior="mvs"))
    dec, vals = _decisions(tmp_path)
    assert vals["ref_source"] == "sfm" and 95 < vals["ref_distance"] < 115  # cameras 110 above the ground
    assert dec["completion"]["applied"] and dec["completion"]["details"]["completed"] > 0.05
    conf = res.confidence
    assert conf.shape == (len(res.points),) and ((conf >= 0) & (conf <= 1)).all()
    assert (conf < 0.5).any() and (conf >= 0.5).any()
    stored = read_ply_confidence(tmp_path / "points.ply")
    assert np.allclose(stored, conf, atol=1e-6)
    fig = _relative_figures(grid_scene, res)
    assert fig["cov_all"] > 0.95 > fig["cov_measured"]
    assert fig["absrel_measured"] < 0.02 and fig["absrel_all"] < 0.04
    # Switched off: only measured points, nothing below 0.5.
    off = initialise(grid_scene, tmp_path / "off", InitConfig(depth_prior="mvs", complete="off"))
    assert (off.confidence >= 0.5).all()
    assert not _decisions(tmp_path / "off")[0]["completion"]["applied"]


@pytest.mark.slow  # 2.6 s; the fast tier reads masks (tests/data/test_no_data.py) and checks the loss
def test_pixels_without_data_are_neither_measured_nor_completed(grid_scene, tmp_path):
    """The same strip with a corner of each training photo holding no data: those pixels get no depth
    from the sweep nor from the height field (completed before: the whole photo), SfM runs on the
    rest, and the other pixels are measured and completed as without the corner."""
    from dataclasses import replace

    from dibrgs_core.data.scene import View

    y, x = np.mgrid[0:96, 0:96]
    ok = x + y >= 48  # an eighth of each photo
    views = {k: View(v.camera, np.where(ok[..., None], v.image, 0).astype(np.float32), v.depth, valid=ok)
             if k in grid_scene.train else v for k, v in grid_scene.views.items()}
    initialise(replace(grid_scene, views=views), tmp_path, InitConfig(depth_prior="mvs"))
    dec, vals = _decisions(tmp_path)
    measured = np.mean(list(vals["prior_coverage"].values()))
    completed = dec["completion"]["details"]["completed"]
    assert dec["completion"]["applied"] and completed > 0.05 and vals["sfm_points"] >= 20
    assert measured + completed <= ok.mean() + 1e-6, (measured, completed, ok.mean())
    assert measured + completed > ok.mean() - 0.05


@pytest.mark.stability
@pytest.mark.slow
def test_geometry_does_not_depend_on_units(grid_scene, tmp_path):
    """The same mapping strip in units x0.001, x1 and x1000 (the real flight is 5.3 units high, generated
    scenes 210 m): the same relative figures (coverage, relative error, point counts)."""
    from geom_synth import scaled_scene

    figs = {}
    for f in (1e-3, 1.0, 1e3):
        sc = scaled_scene(grid_scene, f)
        res = initialise(sc, tmp_path / f"s{f:g}", InitConfig(depth_prior="mvs"))
        assert np.isfinite(res.points).all()
        figs[f] = _relative_figures(sc, res)
        assert abs(_decisions(tmp_path / f"s{f:g}")[1]["ref_distance"] / f - 105) < 10
    base = figs[1.0]
    for f in (1e-3, 1e3):
        for k in ("cov_all", "cov_measured"):
            assert abs(figs[f][k] - base[k]) < 0.005, (f, k, figs[f][k], base[k])
        for k in ("absrel_all", "absrel_measured"):
            assert abs(figs[f][k] - base[k]) < 0.02 * base[k] + 1e-4, (f, k, figs[f][k], base[k])
        for k in ("points", "completed"):
            assert abs(figs[f][k] - base[k]) <= 0.01 * base[k] + 5, (f, k, figs[f][k], base[k])


def _footprint_figures(scene, res):
    """Figures of a geometry result that do not depend on the lens: (coverage of the training pixels by
    the measured points, their median depth error in widths of the ground a view covers)."""
    cov, err = [], []
    keep = res.dense_confidence >= 0.5
    for v in scene.train_views():
        d = zbuffer(v.camera, res.dense_points[keep])
        ok = np.isfinite(d)
        cov.append(ok.mean())
        err.append(np.abs(d[ok] - v.depth[ok]) / (v.depth[ok] * v.camera.span))
    return float(np.mean(cov)), float(np.median(np.concatenate(err)))


@pytest.mark.stability
@pytest.mark.slow
def test_a_telephoto_view_of_the_scene_gets_the_same_geometry(tmp_path):
    """The same orbit seen from 100 x further through a 100 x narrower lens (a satellite's view: nearly
    orthographic, the same ground in the same pixels): the scale follows the ground a view covers,
    not its distance, so the sweep's height range, tolerances and voxels are those of the near view.
    When they followed the distance (the generated city's orbit, `make_scene.py --lens-factor 100`):
    no SfM point (COLMAP's focal-length guard), 7 % of the pixels measured, 15 anchors."""
    near, hf = make_synthetic_scene(64, fov_deg=50.0)
    fov = 2 * np.degrees(np.arctan(np.tan(np.radians(25.0)) / 100))
    far, _ = make_synthetic_scene(64, radius=5000.0, height=11000.0, fov_deg=fov, hf=hf)
    figs, vals = {}, {}
    for name, sc in (("near", near), ("far", far)):
        res = initialise(sc, tmp_path / name, InitConfig(depth_prior="mvs"))
        vals[name] = _decisions(tmp_path / name)[1]
        assert np.isfinite(res.points).all(), name
        figs[name] = _footprint_figures(sc, res)
    assert vals["far"]["sfm_points"] >= 10  # 15 near, 34 far: the long view's matches are more exact
    assert abs(vals["far"]["span"] - vals["near"]["span"] / 100) < 1e-6 * vals["near"]["span"]
    assert abs(vals["far"]["scale"] / vals["near"]["scale"] - 1) < 0.02
    assert abs(vals["far"]["points"] / vals["near"]["points"] - 1) < 0.25, (vals["far"]["points"], vals["near"]["points"])
    assert figs["far"][0] > figs["near"][0] - 0.1 and figs["near"][0] > 0.3, figs
    assert figs["far"][1] < 2 * figs["near"][1] + 1e-3, figs


@pytest.mark.slow
def test_a_redundant_cloud_is_thinned_before_the_overlap_removal(tmp_path):
    """Many views of the same ground give the overlap removal a number of close pairs that grows
    with the square of the density (81 views at 512 px: 21 GB). Above the budget the fused cloud is
    thinned to a random share first, says so, and is as close to the surface; within it, untouched.
    (Twelve 64 px views: a cloud as coarse as its pixels, so the voxel grid loses points here too.)"""
    scene, _ = make_synthetic_scene(64, n_views=12)
    full = initialise(scene, tmp_path / "full", InitConfig(depth_prior="gt"))
    dec, vals = _decisions(tmp_path / "full")
    assert not dec["thinning"]["applied"] and dec["overlap_removal"]["applied"]
    budget = int(vals["overlap_pairs_estimate"] / 16)  # keep about a quarter of the points
    thin = initialise(scene, tmp_path / "thin", InitConfig(depth_prior="gt", max_overlap_pairs=budget))
    dec, vals_thin = _decisions(tmp_path / "thin")
    assert dec["thinning"]["applied"] and "a random 25 % kept" in dec["thinning"]["reason"]
    assert vals_thin["dense_points"] == vals["dense_points"]  # before thinning
    assert abs(vals_thin["dense_points_thinned"] / vals["dense_points"] - 0.25) < 0.01
    assert len(thin.dense_points) < 0.3 * len(full.dense_points)
    assert _mae(scene, thin.points) < 0.02 and _mae(scene, full.points) < 0.02
