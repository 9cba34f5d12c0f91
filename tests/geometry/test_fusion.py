"""Fusion: back-projection, dip test, overlap removal (keep lower), reprojection, voxels, PLY."""
from __future__ import annotations

import numpy as np
import pytest

from dibrgs_core.camera.frame import up_frame
from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.data.ply import read_ply, write_ply
from dibrgs_core.geometry.fusion import (
    backproject_views,
    dip_cells,
    overlap_pairs_drop,
    reproject_max_depth,
    to_frame,
)
from dibrgs_core.geometry.pointcloud import voxel_downsample, zbuffer


def _cam(eye=(0, 0, 100.0), size=32):
    K = np.array([[40.0, 0, size / 2], [0, 40.0, size / 2], [0, 0, 1]])
    return Camera(K, look_at(eye, (0, 0, 0), (0, 1, 0)), size, size, "c")


def test_backproject_then_zbuffer_roundtrip():
    cam = _cam()
    depth = np.full((32, 32), 100.0)
    depth[5, 7] = np.nan
    depth[6, 7] = 0.0
    pts, cols, vid = backproject_views([cam], [depth], [np.ones((32, 32, 3)) * 0.5])
    assert len(pts) == 32 * 32 - 2 and (vid == 0).all() and (cols == 128).all()
    zb = zbuffer(cam, pts)
    assert np.isnan(zb[5, 7]) and np.isnan(zb[6, 7])
    assert np.allclose(zb[np.isfinite(zb)], 100.0)


def test_zbuffer_splat_footprint_nearest_and_farthest():
    """One z-buffer serves fusion (1 pixel, nearest or farthest, NaN holes) and pseudo views
    (footprint splats, 0 for holes): two points on one ray, splatted by their distance."""
    cam = _cam()
    ray = cam.backproject(np.full((32, 32), 1.0)).reshape(32, 32, 3)[16, 16] - cam.center  # pixel (16,16), z=1
    pts = cam.center + np.stack([ray * 60.0, ray * 90.0])  # same pixel, depths 60 and 90
    near = zbuffer(cam, pts)
    far = zbuffer(cam, pts, farthest=True)
    assert near[16, 16] == pytest.approx(60.0) and far[16, 16] == pytest.approx(90.0)
    assert np.isnan(near).sum() == 32 * 32 - 1
    # footprint 6 with f = 40: half-size round(6 * 40 / 60 / 2) = 2 px at z = 60, round(1.33) = 1 px at z = 90
    splat = zbuffer(cam, pts, footprint=6.0, empty=0.0)
    assert np.allclose(splat[14:19, 14:19], 60.0) and (splat > 0).sum() == 25
    assert splat[13, 16] == 0.0
    back = zbuffer(cam, pts, farthest=True, footprint=6.0, empty=0.0)
    assert np.allclose(back[15:18, 15:18], 90.0) and back[14, 14] == pytest.approx(60.0)
    assert zbuffer(cam, pts, footprint=1e9, max_radius=3, empty=0.0).astype(bool).sum() == 49
    behind = zbuffer(cam, cam.center - (pts - cam.center), footprint=6.0)
    assert np.isnan(behind).all()


def _layered_cloud(rng, n=4000, gap=5.0):
    """A ground layer (h~0) with a spurious copy 'gap' above it over half the area."""
    xy = rng.uniform(0, 20, (n, 2))
    h = rng.normal(0, 0.05, n)
    dup = xy[: n // 2][xy[: n // 2, 0] < 10] + rng.normal(0, 0.02, (int((xy[: n // 2, 0] < 10).sum()), 2))
    hd = gap + rng.normal(0, 0.05, len(dup))
    return np.concatenate([np.column_stack([xy, h]), np.column_stack([dup, hd])]), len(dup)


def test_dip_and_keep_lower_removes_upper_layer():
    rng = np.random.default_rng(0)
    local, n_dup = _layered_cloud(rng)
    dip = dip_cells(local, cell=2.0, alpha=0.05, min_points=8)
    assert dip.n_multimodal > 0
    # Only cells on the doubled half are multimodal.
    assert (local[dip.in_multimodal, 0] < 10.5).all()
    drop = overlap_pairs_drop(local, dip.in_multimodal, 2.0, eps_xy=0.1, eps_z=1.0)
    assert drop.any()
    assert (local[drop, 2] > 2.5).all()  # only upper-layer points are dropped
    assert (~drop[local[:, 2] < 2.5]).all()  # the lower layer is untouched


@pytest.mark.stability
def test_dip_stiff_cells():
    """Dip test on a cell of 2 points and on a cell whose heights are all equal: no crash, unimodal, nothing dropped."""
    # A cell of 2 points and a cell with all heights equal: not multimodal, no crash, no drops.
    local = np.array([[0.1, 0.1, 0.0], [0.2, 0.1, 9.0]] + [[5.1 + 0.01 * i, 5.1, 3.0] for i in range(20)])
    dip = dip_cells(local, cell=2.0, alpha=0.05, min_points=4)
    assert dip.n_multimodal == 0 and dip.n_tested == 1 and not dip.in_multimodal.any()
    assert not overlap_pairs_drop(local, dip.in_multimodal, 2.0, 0.1, 1.0).any()
    # Forcing the 2-point cell as candidate still drops exactly the higher point.
    drop = overlap_pairs_drop(local, np.r_[True, True, np.zeros(20, bool)], 2.0, 0.2, 1.0)
    assert drop.tolist()[:2] == [False, True]
    empty = dip_cells(np.zeros((0, 3)), 2.0)
    assert empty.n_cells == 0


@pytest.mark.stability
def test_up_frame_is_used_not_z():
    """The same layered cloud rotated so 'up' is +X: in the up frame the upper layer is found and dropped."""
    rng = np.random.default_rng(1)
    local, _ = _layered_cloud(rng)
    up = np.array([1.0, 0.0, 0.0])
    F = up_frame(up)
    origin = np.array([4.0e5, 1.0e5, 30.0])
    world = local @ F + origin  # local coordinates back to world
    back = to_frame(world, F, origin)
    assert np.allclose(back, local, atol=1e-6)
    dip = dip_cells(back, 2.0)
    drop = overlap_pairs_drop(back, dip.in_multimodal, 2.0, 0.1, 1.0)
    assert drop.any() and (world[drop] @ up - origin @ up > 2.5).all()


def test_reproject_max_depth_keeps_farthest():
    cam = _cam(size=16)
    near = np.full((16, 16), 90.0)
    far = np.full((16, 16), 100.0)
    out = reproject_max_depth([cam, cam], [near, far])
    assert np.allclose(out[0], 100.0) and np.allclose(out[1], 100.0)
    hole = near.copy()
    hole[3, 3] = np.nan
    out = reproject_max_depth([cam, cam], [hole, far])
    assert np.isnan(out[0][3, 3])  # no new coverage in a view's holes


def test_voxel_downsample_and_ply_roundtrip(tmp_path):
    origin = np.array([1e5, 2e5, 0.0])
    pts = origin + np.array([[0.1, 0.1, 0.1], [0.3, 0.2, 0.4], [1.5, 0.1, 0.1]])
    cols = np.array([[0, 0, 0], [100, 200, 50], [9, 9, 9]], np.uint8)
    P, C = voxel_downsample(pts, cols, 1.0, origin)
    assert len(P) == 2
    i = np.argmin(P[:, 0])
    assert np.allclose(P[i] - origin, [0.2, 0.15, 0.25]) and C[i].tolist() == [50, 100, 25]
    write_ply(tmp_path / "p.ply", P, C)
    P2, C2 = read_ply(tmp_path / "p.ply")
    assert np.allclose(P2, P, atol=1e-9) and (C2 == C).all()
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write leaves no temporary behind
    P0, _ = voxel_downsample(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), 1.0)
    assert P0.shape == (0, 3)


def test_voxel_values_and_ply_confidence_roundtrip(tmp_path):
    """A per-point confidence is averaged per voxel and stored as a PLY vertex property that plain
    readers (read_ply, trimesh) ignore; a PLY without one reads as None."""
    from dibrgs_core.data.ply import read_ply_confidence
    from dibrgs_core.geometry.pointcloud import voxel_downsample_values

    pts = np.array([[0.1, 0.1, 0.1], [0.3, 0.2, 0.4], [1.5, 0.1, 0.1]])
    cols = np.array([[0, 0, 0], [100, 200, 50], [9, 9, 9]], np.uint8)
    P, C, K = voxel_downsample_values(pts, cols, np.array([1.0, 0.5, 0.25]), 1.0)
    assert sorted(K.tolist()) == [0.25, 0.75]
    P1, C1 = voxel_downsample(pts, cols, 1.0)
    assert np.allclose(P, P1) and (C == C1).all()
    write_ply(tmp_path / "c.ply", P, C, K)
    P2, C2 = read_ply(tmp_path / "c.ply")
    assert np.allclose(P2, P, atol=1e-6) and (C2 == C).all()
    assert np.allclose(read_ply_confidence(tmp_path / "c.ply"), K)
    write_ply(tmp_path / "plain.ply", P, C)
    assert read_ply_confidence(tmp_path / "plain.ply") is None
    with pytest.raises(ValueError, match="confidences"):
        write_ply(tmp_path / "bad.ply", P, C, K[:1])
    assert not (tmp_path / "bad.ply").exists()


def test_neighbour_pairs_estimate_is_within_a_factor_of_two():
    from scipy.spatial import cKDTree

    from dibrgs_core.geometry.fusion import neighbour_pairs_estimate

    rng = np.random.default_rng(0)
    for n, eps in ((20000, 0.01), (50000, 0.005), (5000, 0.05)):
        xy = rng.uniform(0, 1, (n, 2))
        exact = len(cKDTree(xy).query_pairs(eps, output_type="ndarray"))
        est = neighbour_pairs_estimate(xy * 1000.0, eps * 1000.0)  # units do not matter
        assert 0.5 * exact < est < 2.0 * exact, (n, eps, exact, est)
    assert neighbour_pairs_estimate(np.zeros((0, 2)), 1.0) == 0.0
