"""Tests for dibrgs_core.training.pseudo_views on an analytic two-layer scene with known depth and colour."""
from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest
from threads import torch_threads

from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.data.scene import View
from dibrgs_core.training.pseudo_warp import (
    EMPTY,
    PADDED,
    fill_progressive,
    sample_sources,
    source_order,
    warp_progressive,
)
from dibrgs_core.training.pseudo_views import build_pseudo_views
from dibrgs_core.training.pseudo_depth import complete_depth, remove_see_through, zbuffer_depth

TOP_H = 1.0  # height of the floating square [-0.6,0.6]^2 above the ground plane z=0


def ground_tex(x, y):
    return np.stack([0.5 + 0.4 * np.sin(3 * x), 0.5 + 0.4 * np.cos(2 * y), 0.5 + 0.3 * np.sin(x + y)], -1)


def top_tex(x, y):
    return np.stack([0.9 + 0 * x, 0.1 + 0.05 * np.sin(5 * y), 0.1 + 0 * x], -1)


def cam_at(angle_deg: float, size: int = 64, radius: float = 4.0, height: float = 3.0) -> Camera:
    a = np.radians(angle_deg)
    K = np.array([[size * 0.9, 0, size / 2], [0, size * 0.9, size / 2], [0, 0, 1]])
    eye = [radius * np.cos(a), radius * np.sin(a), height]
    return Camera(K=K, w2c=look_at(eye, [0, 0, 0], [0, 0, 1]), width=size, height=size, name=f"c{angle_deg:g}")


def render(cam: Camera, occluder: bool = True):
    """Ray-cast the scene: (image (H,W,3) float32, z-depth (H,W) float32; 0 where the ray misses)."""
    o, d = cam.pixel_rays()  # d has camera-z 1, so the ray parameter is the z-depth
    with np.errstate(divide="ignore", invalid="ignore"):
        tg = np.where(d[:, 2] < 0, -o[:, 2] / d[:, 2], np.inf)
        tt = np.where(d[:, 2] < 0, (TOP_H - o[:, 2]) / d[:, 2], np.inf)
    pt = o + d * np.where(np.isfinite(tt), tt, 0)[:, None]
    hit_top = occluder & np.isfinite(tt) & (np.abs(pt[:, 0]) <= 0.6) & (np.abs(pt[:, 1]) <= 0.6)
    pg = o + d * np.where(np.isfinite(tg), tg, 0)[:, None]
    img = np.where(hit_top[:, None], top_tex(pt[:, 0], pt[:, 1]), ground_tex(pg[:, 0], pg[:, 1]))
    depth = np.where(hit_top, tt, np.where(np.isfinite(tg), tg, 0))
    H, W = cam.height, cam.width
    return img.reshape(H, W, 3).astype(np.float32), depth.reshape(H, W).astype(np.float32)


def scene_points(step: float = 0.03, occluder: bool = True, extent: float = 4.0) -> np.ndarray:
    g = np.arange(-extent, extent, step)
    x, y = np.meshgrid(g, g)
    pts = [np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)]
    if occluder:
        t = np.arange(-0.6, 0.6 + 1e-9, step)
        x, y = np.meshgrid(t, t)
        pts.append(np.stack([x.ravel(), y.ravel(), np.full(x.size, TOP_H)], 1))
    return np.concatenate(pts)


def test_warp_with_true_depth_reproduces_view():
    a, b = cam_at(0), cam_at(35)
    ia, da = render(a)
    ib, db = render(b)
    img, valid, fb = warp_progressive(b, db, [(a, ia, da)])
    assert valid.mean() > 0.5
    err = np.abs(img - ib)[valid].mean()
    assert err < 0.02
    assert set(np.unique(fb[valid])) == {0}
    assert np.isfinite(img).all() and img.min() >= 0 and img.max() <= 1


def test_occlusion_test_rejects_hidden_pixels():
    # the target looks from the other side: ground behind the square (from the source) is visible in it
    a, b = cam_at(0), cam_at(180)
    ia, da = render(a)
    ib, db = render(b)
    img, valid, fb = warp_progressive(b, db, [(a, ia, da)])
    # analytic visibility of every target pixel's surface point in the source
    X = b.backproject(db)
    uv, z = a.project(X)
    inside = (db.ravel() > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 64) & (uv[:, 1] >= 0) & (uv[:, 1] < 64)
    xi, yi = uv[:, 0].astype(int).clip(0, 63), uv[:, 1].astype(int).clip(0, 63)
    hidden = inside & (z > da[yi, xi] * 1.05)
    assert hidden.sum() > 20  # the setup really has occluded pixels
    assert not valid.ravel()[hidden].any()
    assert np.abs(img - ib)[valid].mean() < 0.03
    # without the test (source depth far behind everything) hidden pixels take the square's colour
    img2, valid2, _ = warp_progressive(b, db, [(a, ia, np.full_like(da, 1e6))])
    assert valid2.ravel()[hidden].all()
    assert np.abs(img2 - ib).reshape(-1, 3)[hidden].mean() > 0.2
    # hidden pixels are padded, not left empty
    assert (fb.ravel()[hidden] == PADDED).all()


def test_progressive_fill_covers_more_and_nearest_first():
    t = cam_at(90)
    it, dt = render(t)
    srcs = [(c, *render(c)) for c in (cam_at(60), cam_at(200), cam_at(330))]
    img1, v1, _ = warp_progressive(t, dt, srcs[:1])
    img3, v3, fb3 = warp_progressive(t, dt, [srcs[2], srcs[1], srcs[0]])  # order given must not matter
    assert v3.sum() > v1.sum() + 50
    assert (v3 | ~v1).all()  # everything the nearest source filled stays filled ...
    assert (fb3[v1] == 2).all()  # ... by it (index 2 in the list given)
    assert np.abs(img3 - it)[v3].mean() < 0.03
    assert (fb3 != EMPTY).all()  # padded everywhere else


def test_zbuffer_and_completion_match_true_depth():
    cam = cam_at(20, radius=3.0, height=5.0)  # oblique, but not grazing (z-buffer bias grows at grazing rows)
    _, dtrue = render(cam)
    pts = scene_points(step=0.08, extent=14.0)  # sparse: several pixels per point near the camera
    raw = zbuffer_depth(pts, cam)
    assert (raw > 0).mean() > 0.9
    filled = complete_depth(raw)
    assert (filled > 0).all() and np.isfinite(filled).all()
    rel = np.abs(filled - dtrue) / dtrue
    assert np.mean(rel < 0.02) > 0.95
    # without splat footprints the same cloud leaves holes
    assert (zbuffer_depth(pts, cam, spacing=0.0) > 0).mean() < (raw > 0).mean()


def test_see_through_speckles_removed_edges_kept():
    d = np.full((20, 20), 10.0, np.float32)
    d[:, 10:] = 20.0  # a genuine occlusion edge
    d[5, 4] = d[12, 6] = 20.0  # background leaking through the foreground
    out = remove_see_through(d)
    assert out[5, 4] == 0 and out[12, 6] == 0
    assert (out[:, 10:] == 20).all() and (out[:, :10][out[:, :10] > 0] == 10).all()
    filled = complete_depth(d)
    assert filled[5, 4] == 10 and filled[12, 6] == 10 and filled[3, 15] == 20


@pytest.mark.stability
def test_empty_inputs_are_handled():
    """Pseudo view from an empty point cloud / empty depth: empty mask, finite image, no crash."""
    cam = cam_at(0, size=16)
    assert (zbuffer_depth(np.zeros((0, 3)), cam) == 0).all()
    assert (complete_depth(np.zeros((16, 16))) == 0).all()
    img, valid, fb = warp_progressive(cam, np.zeros((16, 16)), [(cam_at(30, 16), np.ones((16, 16, 3)))])
    assert not valid.any() and (fb == EMPTY).all() and np.isfinite(img).all()
    # all points behind the camera
    behind = np.array([[8.0, 0, 6.0], [9.0, 1.0, 7.0]])
    assert (zbuffer_depth(behind, cam) == 0).all()


def test_build_pseudo_views_cache(tmp_path):
    views = [View(camera=c, image=render(c)[0]) for c in (cam_at(0, 48), cam_at(120, 48), cam_at(240, 48))]
    pts = scene_points(step=0.05)
    built = build_pseudo_views(views, pts, n=2, seed=0, cache_dir=tmp_path)
    pvs = built.views
    assert len(pvs) == 2 and (tmp_path / "manifest.json").is_file() and not built.cached
    assert built.trajectory.kind == "orbit" and built.tried >= 2 and built.cpu_s > 0
    for pv in pvs:
        assert pv.image.shape == (48, 48, 3) and pv.image.dtype == np.float32
        assert pv.valid.mean() > 0.3 and not (pv.valid & pv.padded).any()
        ref, _ = render(pv.camera)
        assert np.abs(pv.image - ref)[pv.valid].mean() < 0.05
    # the manifest keeps each kept view's fractions (the log has them at debug level only)
    listed = json.loads((tmp_path / "manifest.json").read_text())["views"]
    assert [v["name"] for v in listed] == [pv.camera.name for pv in pvs]
    for v, pv in zip(listed, pvs):
        assert v["warped"] == pytest.approx(pv.valid.mean()) and v["padded"] == pytest.approx(pv.padded.mean())
        assert 0.0 <= v["rejected"] <= 1.0 - v["warped"] - v["padded"] + 1e-9
    again = build_pseudo_views(views, pts, n=2, seed=0, cache_dir=tmp_path)
    assert again.cached and again.tried == built.tried and again.trajectory.kind == "orbit"
    for a, b in zip(pvs, again.views):
        assert np.array_equal(a.image, b.image) and np.array_equal(a.valid, b.valid)
        assert np.array_equal(a.depth, b.depth) and np.array_equal(a.padded, b.padded)
        assert np.allclose(a.camera.w2c, b.camera.w2c) and a.camera.name == b.camera.name
    other = build_pseudo_views(views, pts, n=2, seed=1, cache_dir=tmp_path)
    assert not other.cached and not np.allclose(other.views[0].camera.w2c, pvs[0].camera.w2c)
    # no points at all: no view is kept (the cloud covers none), no crash
    empty = build_pseudo_views(views, np.zeros((0, 3)), n=1, seed=0, cache_dir=tmp_path / "e")
    assert empty.views == [] and empty.dropped_cloud == empty.tried == 3
    # a user path is kept whole, even a view the cloud does not cover
    path = build_pseudo_views(views, np.zeros((0, 3)), n=5, seed=0, cache_dir=tmp_path / "p", path=[cam_at(60, 48)])
    assert len(path.views) == 1 and path.trajectory is None and path.views[0].camera.name == "c60"
    assert not path.views[0].valid.any() and np.isfinite(path.views[0].image).all()
    # ... and the poses that are mostly padding are named, also when the path loads from the cache
    away = Camera(K=cam_at(60, 48).K, w2c=look_at([30.0, 0, 3.0], [30.0, 0.1, 0], [0, 0, 1]), width=48, height=48,
                  name="away")
    on_off = [cam_at(60, 48), away]
    for _ in range(2):
        mixed = build_pseudo_views(views, pts, n=5, seed=0, cache_dir=tmp_path / "q", path=on_off)
        assert [pv.camera.name for pv in mixed.views] == ["c60", "away"] and mixed.thin == ["away"]
        assert mixed.views[0].valid.mean() > 0.3 and mixed.views[1].valid.mean() < 0.2
    assert mixed.cached and not built.thin


def test_cache_is_never_reused_by_another_split_or_scene(tmp_path):
    """One cache folder, several inputs: another training split, another scene (same cameras, other
    images), other cameras, another cloud, other options each rebuild; only identical inputs load."""
    cams = [cam_at(a, 40) for a in (0, 90, 180, 270)]
    views = [View(camera=c, image=render(c)[0]) for c in cams]
    pts = scene_points(step=0.06)
    cache = tmp_path / "pseudo"

    def build(vs, p=pts, **kw):
        return build_pseudo_views(vs, p, n=2, seed=0, cache_dir=cache, **kw)

    first = build(views[:3])
    assert not first.cached and build(views[:3]).cached
    split = build([views[0], views[1], views[3]])  # another split of the same scene
    assert not split.cached
    flat = [View(camera=v.camera, image=render(v.camera, occluder=False)[0]) for v in views[:3]]
    scene2 = build(flat)  # another scene seen by the same cameras
    assert not scene2.cached
    for a, b in zip(first.views, scene2.views):  # rebuilt from the other images, not the cached ones
        assert not np.array_equal(a.image, b.image)
    moved = [View(camera=Camera(K=c.K, w2c=look_at(c.center * 1.01, [0, 0, 0], [0, 0, 1]), width=40, height=40,
                                name=c.name), image=v.image) for c, v in zip(cams[:3], views[:3])]
    assert not build(moved).cached
    assert not build(views[:3], p=pts + 1e-9).cached
    assert not build(views[:3], consistency_tol=0.1).cached
    assert not build(views[:3], min_warped=0.3).cached
    assert build(views[:3], min_warped=0.3).cached


def test_sampled_views_are_filtered_by_cloud_cover_and_warped_share(tmp_path):
    """Poses whose view the cloud barely covers are skipped; views with too few warped pixels are
    dropped; up to 3 x n poses are tried to keep n."""
    views = [View(camera=c, image=render(c)[0]) for c in (cam_at(0, 40), cam_at(120, 40), cam_at(240, 40))]
    pts = scene_points(step=0.06)
    some = pts[pts[:, 0] > 2.5]  # a strip of ground at one side: most views see little of it
    loose = build_pseudo_views(views, some, n=6, seed=0, cache_dir=tmp_path / "a", min_cloud_cover=0.0,
                               min_warped=0.0)
    strict = build_pseudo_views(views, some, n=6, seed=0, cache_dir=tmp_path / "b", min_cloud_cover=0.25,
                                min_warped=0.0)
    assert len(loose.views) == 6 and loose.dropped_cloud == 0
    assert strict.dropped_cloud > 0 and strict.tried <= 18
    assert len(strict.views) + strict.dropped_cloud == strict.tried
    from scipy import ndimage

    for pv in strict.views:  # share of pixels within 4 px of a pixel the cloud projects to
        raw = zbuffer_depth(some, pv.camera)
        assert (ndimage.distance_transform_edt(raw <= 0) <= 4.0).mean() >= 0.25
    warped = build_pseudo_views(views, pts, n=6, seed=0, cache_dir=tmp_path / "c", min_warped=0.75)
    assert warped.dropped_warped > 0 and all(pv.valid.mean() >= 0.75 for pv in warped.views)
    fr = warped.mean_fractions()
    assert fr["warped"] == pytest.approx(np.mean([pv.valid.mean() for pv in warped.views]))
    assert 0 <= fr["padded"] <= 1 and fr["rejected"] == 0.0


@pytest.mark.parametrize("threads", [2, 3])
def test_views_built_ahead_on_threads_are_the_ones_built_one_by_one(tmp_path, threads):
    """Torch's thread count of views in flight: the same poses tried, kept and dropped, in the same
    order, with the same pixels, as one at a time; and no more tried than one at a time needs."""
    views = [View(camera=c, image=render(c)[0]) for c in (cam_at(0, 40), cam_at(120, 40), cam_at(240, 40))]
    pts = scene_points(step=0.06)
    some = pts[pts[:, 0] > 1.5]
    built = {}
    for t in (1, threads):
        with torch_threads(t):
            built[t] = build_pseudo_views(views, some, n=4, seed=0, cache_dir=tmp_path / str(t), min_cloud_cover=0.25,
                                          min_warped=0.2, surface=True, consistency_tol=0.1)
    a, b = built[1], built[threads]
    # Both filters drop poses, and n is reached before the 3 n candidates run out.
    assert a.dropped_cloud > 0 and a.dropped_warped > 0 and len(a.views) == 4 and a.tried < 12
    assert (a.tried, a.dropped_cloud, a.dropped_warped, len(a.views)) == (b.tried, b.dropped_cloud,
                                                                          b.dropped_warped, len(b.views))
    for x, y in zip(a.views, b.views):
        assert x.camera.name == y.camera.name and np.array_equal(x.camera.w2c, y.camera.w2c)
        assert np.array_equal(x.image, y.image) and np.array_equal(x.valid, y.valid)
        assert np.array_equal(x.padded, y.padded) and np.array_equal(x.rejected, y.rejected)


def test_speed_256():
    t = cam_at(90, size=256)
    pts = scene_points(step=0.02)  # 160k points
    srcs = [(c, *render(c)) for c in (cam_at(60, 256), cam_at(200, 256), cam_at(330, 256))]
    t0 = time.perf_counter()
    depth = complete_depth(zbuffer_depth(pts, t, spacing=0.02))
    warp_progressive(t, depth, srcs)
    dt = time.perf_counter() - t0
    assert dt < 3.0, f"{dt:.2f}s for one 256x256 pseudo view"


def test_generated_scene_warp_with_gt_depth(tiny_scene):
    """On the rendered city: view 001 warped into 002's pose with GT depth reproduces 002."""
    from dibrgs_core.data.levir import read_scene

    v = read_scene(tiny_scene).views
    a, b = v["001"], v["002"]
    img, valid, _ = warp_progressive(b.camera, b.depth, [(a.camera, a.image, a.depth)])
    assert valid.mean() > 0.5
    err = np.abs(img - b.image)[valid].mean()
    unwarped = np.abs(a.image - b.image)[valid].mean()
    assert err < 0.05 and err < 0.5 * unwarped


@pytest.mark.slow
def test_eval_pseudo_views_script_ranks_oracle_depth_above_mvs(tiny_scene, tmp_path):
    """scripts/eval_pseudo_views.py on the generated 64x64 city: a table row per prior, finite
    figures, and pseudo views from ground-truth depth closer to the held-out images than from MVS."""
    import json
    import subprocess
    import sys

    from paths import REPO

    out = tmp_path / "pv.json"
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "eval_pseudo_views.py"), str(tiny_scene),
                        "--priors", "mvs,gt", "--json", str(out)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "| mvs |" in r.stdout and "| gt |" in r.stdout
    res = {x["prior"]: x for x in json.loads(out.read_text())}
    for x in res.values():
        assert len(x["views"]) == 17 and 0.0 < x["valid"] <= 1.0
        assert np.isfinite(x["psnr_all"]) and 8.0 < x["psnr_all"] < 60.0
    assert res["gt"]["psnr_all"] > res["mvs"]["psnr_all"]


def reference_warp(target: Camera, depth: np.ndarray, sources: list[tuple]):
    """The per-source loop the vectorised warp replaced: back-project, ``Camera.project`` into each
    source, occlusion test, bilinear lookup (pixel centres at +0.5, clamped), nearest source first;
    then the same two paddings."""
    from scipy import ndimage

    H, W = target.height, target.width
    has = (depth > 0).ravel()
    X = target.backproject(np.where(depth > 0, depth, 1.0))
    img, valid = np.zeros((H * W, 3)), np.zeros(H * W, bool)
    filled = np.full(H * W, EMPTY)
    seen, pad_src = np.zeros(H * W, bool), np.full(H * W, -1)

    def bilinear(im, uv):
        h, w = im.shape[:2]
        x, y = np.clip(uv[:, 0] - 0.5, 0, w - 1), np.clip(uv[:, 1] - 0.5, 0, h - 1)
        x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
        x1, y1, ax, ay = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1), (x - x0)[:, None], (y - y0)[:, None]
        return (im[y0, x0] * (1 - ax) + im[y0, x1] * ax) * (1 - ay) + (im[y1, x0] * (1 - ax) + im[y1, x1] * ax) * ay

    order = np.argsort([np.linalg.norm(s[0].center - target.center) for s in sources], kind="stable")
    for k in order:
        cam, im, ds = sources[k]
        uv, z = cam.project(X)
        front = has & (z > 0)
        pad_src[(pad_src < 0) & front] = k
        inside = front & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        seen |= inside
        i = np.flatnonzero(inside & ~valid)
        d = ds[uv[i, 1].astype(int).clip(0, cam.height - 1), uv[i, 0].astype(int).clip(0, cam.width - 1)]
        i = i[(d > 0) & (z[i] <= d * 1.02)]
        img[i], valid[i], filled[i] = bilinear(im, uv[i]), True, k
    out = ~valid & ~seen & (pad_src >= 0)
    for k in np.unique(pad_src[out]):
        i = np.flatnonzero(out & (pad_src == k))
        img[i] = bilinear(sources[k][1], sources[k][0].project(X[i])[0])
        filled[i] = PADDED
    done = filled != EMPTY
    if done.any() and not done.all():
        ii = ndimage.distance_transform_edt(~done.reshape(H, W), return_distances=False, return_indices=True)
        near = (ii[0] * W + ii[1]).ravel()
        img[~done], filled[~done] = img[near[~done]], PADDED
    return img.reshape(H, W, 3), valid.reshape(H, W), filled.reshape(H, W)


def test_vectorised_warp_matches_the_per_source_reference(tiny_scene):
    """Stated tolerance: the one-projection-per-source warp gives the reference's masks and filling
    sources exactly and its colours within 1e-5, on the analytic scene (with occlusion) and on the
    generated city with its exact depth."""
    from dibrgs_core.data.levir import read_scene

    cases = []
    t = cam_at(90, 64)
    cases.append((t, render(t)[1], [(c, *render(c)) for c in (cam_at(60), cam_at(200), cam_at(330))]))
    v = read_scene(tiny_scene).views
    cases.append((v["005"].camera, v["005"].depth,
                  [(v[k].camera, v[k].image, v[k].depth) for k in ("001", "008", "015")]))
    for target, depth, sources in cases:
        ref_img, ref_valid, ref_filled = reference_warp(target, depth, sources)
        img, valid, filled = warp_progressive(target, depth, sources)
        assert np.array_equal(valid, ref_valid) and np.array_equal(filled, ref_filled)
        assert np.abs(img - ref_img).max() < 1e-5
        assert valid.mean() > 0.3 and (filled == PADDED).any()
        # The parts agree with the whole: per-source samples, nearest-first fill.
        s = sample_sources(target, depth, sources)
        img2, valid2, _ = fill_progressive(s, source_order(target, sources), depth.shape)
        assert np.array_equal(img2, img) and np.array_equal(valid2, valid)


def test_setup_reports_the_trajectory_and_the_kept_views(tmp_path):
    """``training.setup.pseudo_frames``: a decision ``pseudo_trajectory`` with the class and why,
    values ``pseudo_views`` (kept, tried, dropped, mean warped / padded / rejected) and weighted frames;
    a user path overrides the trajectory (and says so)."""
    import json

    from dibrgs_core.camera.serialize import camera_to_dict
    from dibrgs_core.common.report import Report
    from dibrgs_core.training.config import preset
    from dibrgs_core.training.frames import views_to_frames
    from dibrgs_core.training.setup import SetupContext, pseudo_frames

    views = [View(camera=c, image=render(c)[0]) for c in (cam_at(0, 40), cam_at(120, 40), cam_at(240, 40))]
    cfg = preset("test")
    cfg.pseudo.n_views = 5

    def run(work, cfg, points=scene_points(step=0.06)):
        rep = Report()
        ctx = SetupContext(cfg, work, None, views_to_frames(views, 1.0), rep, np.random.default_rng(0), None)
        return pseudo_frames(ctx, points), rep

    frames, rep = run(tmp_path / "a", cfg)
    d = {x.step: x for x in rep.decisions}
    assert d["pseudo_trajectory"].applied and d["pseudo_trajectory"].reason.startswith("orbit: ")
    assert d["pseudo_trajectory"].details["kind"] == "orbit"
    v = rep.values["pseudo_views"]
    assert v["kept"] == len(frames) == 5 and v["wanted"] == 5 and v["tried"] >= 5 and not v["cached"]
    assert 0.3 < v["mean_warped"] <= 1 and 0 <= v["mean_padded"] < 1 and 0 <= v["mean_rejected"] < 0.5
    assert "along the orbit trajectory" in d["pseudo_views"].reason
    # Dropped poses are counted by reason, and a reason that dropped none is not named (a strip of
    # ground at one side of the scene: most sampled views see too little of it).
    strip = scene_points(step=0.06)
    _, rep_strip = run(tmp_path / "strip", cfg, strip[strip[:, 0] > 2.5])
    for r in (rep, rep_strip):
        v, reason = r.values["pseudo_views"], {x.step: x for x in r.decisions}["pseudo_views"].reason
        counts = {"where the cloud covered too little": v["dropped_no_cloud"],
                  "with too little warped": v["dropped_few_warped"]}
        for what, n in counts.items():
            assert (f"{n} {what}" in reason) == (n > 0), reason
        assert ("sampled poses dropped" in reason) == (sum(counts.values()) > 0), reason
    assert rep_strip.values["pseudo_views"]["dropped_no_cloud"] > 0
    v = rep.values["pseudo_views"]
    for f in frames:
        assert f.mask.shape == (40, 40) and float(f.mask.max()) == 1.0
    _, rep2 = run(tmp_path / "a", cfg)
    assert rep2.values["pseudo_views"]["cached"] and rep2.values["pseudo_views"]["kept"] == 5
    path = tmp_path / "path.json"
    path.write_text(json.dumps([camera_to_dict(cam_at(a, 40)) for a in (30, 60)]))
    cfg.pseudo_path = str(path)
    frames, rep = run(tmp_path / "b", cfg)
    d = {x.step: x for x in rep.decisions}
    assert not d["pseudo_trajectory"].applied and str(path) in d["pseudo_trajectory"].reason
    assert len(frames) == 2 and rep.values["pseudo_views"]["wanted"] == 2
    # Training on images resized by 1/2: the path's cameras (in the scene's pixels) are resized with
    # them, so pseudo views are built and supervised at the training views' resolution.
    half = views_to_frames(views, 0.5)
    ctx = SetupContext(cfg, tmp_path / "c", None, half, Report(), np.random.default_rng(0), None,
                       resolution_scale=0.5)
    small = pseudo_frames(ctx, scene_points(step=0.06))
    assert len(small) == 2
    for f, full in zip(small, frames):
        assert f.image.shape == (20, 20, 3) and f.mask.shape == (20, 20)
        np.testing.assert_allclose(f.cam.cam.K[:2], full.cam.cam.K[:2] * 0.5)


def test_a_user_path_as_a_cams_folder_or_a_colmap_model_gives_the_same_views(tmp_path):
    """``--pseudo-path`` reads what ``dibrgs render --cameras`` reads: a folder of LEVIR Cams files
    and a COLMAP model give the pseudo views of the JSON list of the same cameras (a folder used to
    fail on reading the path's digest, after the geometry stage)."""
    from dibrgs_core.camera.serialize import camera_to_dict
    from dibrgs_core.common.report import Report
    from dibrgs_core.data.colmap import write_colmap_model
    from dibrgs_core.data.levir import write_cams_file
    from dibrgs_core.training.config import preset
    from dibrgs_core.training.frames import views_to_frames
    from dibrgs_core.training.run_folder import PSEUDO_PATH_DIGEST
    from dibrgs_core.training.setup import SetupContext, pseudo_frames

    views = [View(camera=c, image=render(c)[0]) for c in (cam_at(0, 40), cam_at(120, 40), cam_at(240, 40))]
    path_cams = [cam_at(a, 40) for a in (30, 60)]
    for i, c in enumerate(path_cams):
        c.name = f"p{i}"
    listed = tmp_path / "path.json"
    listed.write_text(json.dumps([camera_to_dict(c) for c in path_cams]))
    folder = tmp_path / "cams"
    folder.mkdir()
    for c in path_cams:
        write_cams_file(folder / f"{c.name}.txt", c)
    model = write_colmap_model(path_cams, tmp_path / "colmap" / "sparse" / "0")
    got = {}
    for name, where in (("json", listed), ("cams", folder), ("colmap", model.parent.parent)):
        cfg = preset("test")
        cfg.pseudo_path = str(where)
        rep = Report()
        ctx = SetupContext(cfg, tmp_path / f"w_{name}", None, views_to_frames(views, 1.0), rep,
                           np.random.default_rng(0), None)
        got[name] = (pseudo_frames(ctx, scene_points(step=0.06)), rep)
        assert rep.values[PSEUDO_PATH_DIGEST] and f"on the path {where}" in {
            x.step: x for x in rep.decisions}["pseudo_views"].reason
    ref, _ = got["json"]
    assert len(ref) == 2 and float(ref[0].mask.mean()) > 0.3
    for name in ("cams", "colmap"):
        frames, _ = got[name]
        assert len(frames) == 2
        for f, r in zip(frames, ref):
            np.testing.assert_allclose(f.cam.cam.w2c, r.cam.cam.w2c, atol=1e-6)
            assert float((f.image - r.image).abs().max()) < 0.02 and float((f.mask != r.mask).float().mean()) < 0.01


def test_a_user_path_is_read_in_the_world_frame_of_the_scenes_files(tmp_path):
    """A scene far from its coordinate origin trains in a frame of its own (``Scene.origin``); a
    pseudo path drawn in the files' frame (as the add-on draws it) gives the pseudo views of the
    same path in the scene's frame."""
    from dibrgs_core.camera.serialize import camera_to_dict
    from dibrgs_core.common.report import Report
    from dibrgs_core.data.scene import Scene
    from dibrgs_core.training.config import preset
    from dibrgs_core.training.frames import views_to_frames
    from dibrgs_core.training.setup import SetupContext, pseudo_frames

    views = [View(camera=c, image=render(c)[0]) for c in (cam_at(0, 40), cam_at(120, 40), cam_at(240, 40))]
    origin = np.array([4.0e6, -3.0e6, 2.0e5])
    path_cams = [cam_at(a, 40) for a in (30, 60)]
    cfg = preset("test")
    cfg.pseudo_path = str(tmp_path / "path.json")
    Path(cfg.pseudo_path).write_text(json.dumps([camera_to_dict(c.translated(origin)) for c in path_cams]))
    scene = Scene(root=tmp_path, views={v.name: v for v in views}, origin=origin)
    ctx = SetupContext(cfg, tmp_path / "w", scene, views_to_frames(views, 1.0), Report(), np.random.default_rng(0),
                       None)
    frames = pseudo_frames(ctx, scene_points(step=0.06))
    assert len(frames) == 2
    for f, c in zip(frames, path_cams):
        np.testing.assert_allclose(f.cam.cam.center, c.center, atol=1e-6)
        assert float(f.mask.mean()) > 0.5  # the views warp the scene, not empty space 4e6 away


@pytest.mark.slow
def test_eval_pseudo_views_script_scores_a_given_cloud_and_times_sampled_views(tiny_scene, tmp_path):
    """--points scores a PLY (here the generated city's exact depth, back-projected), --pseudo builds
    sampled views as training does (trajectory, kept/tried, shares, CPU s), --png draws them; a missing
    PLY is one clear line and exit 2."""
    import json
    import subprocess
    import sys

    from paths import REPO
    from dibrgs_core.data.levir import read_scene
    from dibrgs_core.data.ply import write_ply

    sc = read_scene(tiny_scene)
    pts = np.concatenate([v.camera.backproject(v.depth)[(v.depth > 0).ravel()] for v in sc.train_views()])
    ply = tmp_path / "cloud.ply"
    write_ply(ply, pts, np.full((len(pts), 3), 128, np.uint8))
    script = str(REPO / "scripts" / "eval_pseudo_views.py")
    out, png = tmp_path / "r.json", tmp_path / "m.png"
    r = subprocess.run([sys.executable, script, str(tiny_scene), "--priors", "", "--points", f"exact={ply}",
                        "--pseudo", "3", "--consistency-tol", "0.1", "--json", str(out), "--png", str(png)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "| exact |" in r.stdout and "| exact | orbit | 64x64 | 3 / 3" in r.stdout
    res = json.loads(out.read_text())[0]
    s = res["sampled"]
    assert s["trajectory"] == "orbit" and s["kept"] == 3 and s["tried"] >= 3 and s["cpu_s"] > 0
    assert 0.3 < s["warped"] <= 1 and abs(s["warped"] + s["padded"] + s["rejected"] - 1) < 0.05
    assert png.is_file() and png.stat().st_size > 1000
    bad = subprocess.run([sys.executable, script, str(tiny_scene), "--priors", "", "--points", str(tmp_path / "no.ply")],
                         capture_output=True, text=True, timeout=600)
    assert bad.returncode == 2 and "no.ply" in bad.stderr and len(bad.stderr.strip().splitlines()) == 1
