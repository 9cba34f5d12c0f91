"""Fusing per-view depth maps into one point cloud, and removing stacked layers.

All geometry here is done in a *local up frame*: ``F @ (X - origin)`` with
``F = cameras.up_frame(up)`` (rows e1, e2, up), so the first two coordinates
are horizontal and the third is the height; the up axis comes from the
cameras (not assumed +Z) and the local origin keeps float precision for
georeferenced coordinates.

Refinements (the paper's "Refine" column):

* ``none``: every back-projected pixel (plain z-buffer fusion).
* ``reproject``: per view, the farthest depth any view puts on each pixel
  (multi-view maximum depth), back-projected.
* ``no-ovlp``: ours. In horizontal cells whose heights the dip test finds
  multimodal (p < alpha), pairs closer than ``eps_xy`` horizontally and
  farther than ``eps_z`` vertically are overlaps; the higher point of each
  pair is dropped ("keep lower").
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from .cameras import Camera
from .io_levir import to_uint8

log = logging.getLogger("dibrgs.fusion")

REFINES = ("none", "reproject", "no-ovlp")


def to_frame(points: np.ndarray, frame: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """World (N,3) -> local up-frame coordinates (e1, e2, height)."""
    return (np.asarray(points, np.float64) - origin) @ np.asarray(frame).T


def backproject_views(cameras: Sequence[Camera], depths: Sequence[np.ndarray], images: Sequence[np.ndarray]
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project every finite, positive depth pixel (paper eq. 3).

    Returns (points (N,3) float64 world, colors (N,3) uint8, view index (N,)).
    """
    P, C, V = [], [], []
    for i, (cam, d, im) in enumerate(zip(cameras, depths, images)):
        d = np.asarray(d, np.float64).reshape(-1)
        ok = np.isfinite(d) & (d > 0)
        if not ok.any():
            continue
        X = cam.backproject(np.where(ok, d, 0).reshape(cam.height, cam.width))[ok]
        col = to_uint8(np.asarray(im)[..., :3])
        P.append(X)
        C.append(col.reshape(-1, 3)[ok])
        V.append(np.full(ok.sum(), i, np.int32))
    if not P:
        return np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int32)
    return np.concatenate(P), np.concatenate(C), np.concatenate(V)


def zbuffer(cam: Camera, points: np.ndarray, farthest: bool = False, footprint: float = 0.0,
            max_radius: int = 4, empty: float = np.nan) -> np.ndarray:
    """Depth image (H,W, float64 z-depth) of ``points`` seen by ``cam``: the nearest point per pixel
    (or the farthest), ``empty`` where none lands.

    With ``footprint`` (world units, e.g. the cloud's point spacing) each point is splatted as a
    square of half-size ``round(footprint * f / z / 2)`` pixels, at most ``max_radius``, so a
    sparse cloud still covers the image; 0 writes only the pixel the point falls in.
    """
    H, W = cam.height, cam.width
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    acc = np.full(H * W, -np.inf if farthest else np.inf)
    if len(pts):
        uv, z = cam.project(pts)
        ok = (z > 0) & np.isfinite(z) & np.isfinite(uv).all(1)
        uv, z = uv[ok], z[ok]
        f = 0.5 * (cam.fx + cam.fy)
        r = np.clip(np.round(0.5 * footprint * f / z), 0, max_radius).astype(np.int64)
        u = np.floor(uv[:, 0]).astype(np.int64)
        v = np.floor(uv[:, 1]).astype(np.int64)
        near = (u >= -r) & (u < W + r) & (v >= -r) & (v < H + r)
        u, v, z, r = u[near], v[near], z[near], r[near]
        reduce = np.maximum.at if farthest else np.minimum.at
        R = int(r.max()) if len(r) else 0
        for dy in range(-R, R + 1):
            for dx in range(-R, R + 1):
                m = r >= max(abs(dx), abs(dy))
                x, y = u[m] + dx, v[m] + dy
                inside = (x >= 0) & (x < W) & (y >= 0) & (y < H)
                reduce(acc, y[inside] * W + x[inside], z[m][inside])
    return np.where(np.isfinite(acc), acc, empty).reshape(H, W)


def reproject_max_depth(cameras: Sequence[Camera], depths: Sequence[np.ndarray]) -> list[np.ndarray]:
    """The "Reproject" refinement: per view and pixel, the farthest depth of all views' points."""
    pts, _, _ = backproject_views(cameras, depths, [np.zeros((c.height, c.width, 3)) for c in cameras])
    out = []
    for cam, d in zip(cameras, depths):
        far = zbuffer(cam, pts, farthest=True)
        own = np.asarray(d, np.float64)
        # Only pixels the view itself observed keep a depth (no new coverage).
        out.append(np.where(np.isfinite(own) & (own > 0), np.fmax(far, own), np.nan))
    return out


@dataclass
class DipResult:
    """Per-point flag of lying in a multimodal cell, and cell statistics."""

    in_multimodal: np.ndarray
    n_cells: int
    n_tested: int
    n_multimodal: int


def _cell_ids(xy: np.ndarray, cell: float) -> np.ndarray:
    ij = np.floor(xy / cell).astype(np.int64)
    ij -= ij.min(axis=0) if len(ij) else 0
    return ij[:, 0] * (int(ij[:, 1].max()) + 1 if len(ij) else 1) + ij[:, 1]


def dip_cells(local: np.ndarray, cell: float, alpha: float = 0.05, min_points: int = 4) -> DipResult:
    """Hartigan's dip test on the heights of every horizontal cell with >= ``min_points`` points.

    ``local`` is in up-frame coordinates. Cells with fewer points (the test is
    invalid for n <= 3) are treated as unimodal. A cell whose heights are all
    equal has dip 0 and is unimodal.
    """
    import warnings

    import diptest

    n = len(local)
    flags = np.zeros(n, bool)
    if n == 0:
        return DipResult(flags, 0, 0, 0)
    ids = _cell_ids(local[:, :2], cell)
    order = np.argsort(ids, kind="stable")
    sid = ids[order]
    starts = np.flatnonzero(np.r_[True, sid[1:] != sid[:-1]])
    ends = np.r_[starts[1:], n]
    tested = multi = 0
    h = local[order, 2]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for s, e in zip(starts, ends):
            if e - s < max(min_points, 4):
                continue
            tested += 1
            z = h[s:e]
            if np.ptp(z) <= 0:
                continue
            _, p = diptest.diptest(z)
            if p < alpha:
                multi += 1
                flags[order[s:e]] = True
    return DipResult(flags, len(starts), tested, multi)


def overlap_pairs_drop(local: np.ndarray, candidates: np.ndarray, cell: float, eps_xy: float, eps_z: float) -> np.ndarray:
    """Mask of points to drop: the higher point of every overlapping pair (paper eq. 5).

    Pairs are searched with a cKDTree on the horizontal coordinates of the
    ``candidates`` (points in multimodal cells), within the same cell.
    """
    from scipy.spatial import cKDTree

    drop = np.zeros(len(local), bool)
    idx = np.flatnonzero(candidates)
    if len(idx) < 2:
        return drop
    sub = local[idx]
    cells = _cell_ids(sub[:, :2], cell)
    tree = cKDTree(sub[:, :2])
    pairs = tree.query_pairs(eps_xy, output_type="ndarray")
    if len(pairs) == 0:
        return drop
    i, j = pairs[:, 0], pairs[:, 1]
    keep = (cells[i] == cells[j]) & (np.abs(sub[i, 2] - sub[j, 2]) > eps_z)
    i, j = i[keep], j[keep]
    higher = np.where(sub[i, 2] > sub[j, 2], i, j)
    drop[idx[np.unique(higher)]] = True
    return drop


def voxel_keys(points: np.ndarray, voxel: float, origin: np.ndarray | None = None) -> np.ndarray:
    """(N,3) int64 index of the voxel of side ``voxel`` (world axes, relative to ``origin``) holding each point."""
    origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
    return np.floor((np.asarray(points, np.float64) - origin) / voxel).astype(np.int64)


def _flat_keys(keys: np.ndarray) -> np.ndarray:
    """(N,3) int64 voxel keys as one sortable key per row, in the rows' lexicographic order (a 1-D
    ``np.unique`` is several times faster than ``axis=0``); rows themselves when the span overflows int64."""
    k = keys - keys.min(0)
    span = k.max(0).astype(np.float64) + 1
    if span.prod() >= 2.0 ** 62:
        return np.unique(keys, axis=0, return_inverse=True)[1].reshape(-1)
    s1, s2 = int(span[1]), int(span[2])
    return (k[:, 0] * s1 + k[:, 1]) * s2 + k[:, 2]


def voxel_downsample(points: np.ndarray, colors: np.ndarray, voxel: float, origin: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Mean position and colour per occupied voxel of side ``voxel`` (world axes, relative to ``origin``)."""
    P, C, _ = voxel_downsample_values(points, colors, None, voxel, origin)
    return P, C


def voxel_downsample_values(points: np.ndarray, colors: np.ndarray, values: np.ndarray | None, voxel: float,
                            origin: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`voxel_downsample`, also averaging per-point ``values`` (N,) such as a confidence (None: none)."""
    vals = None if values is None else np.asarray(values, np.float64).reshape(-1)
    if len(points) == 0 or not voxel or voxel <= 0:
        return np.asarray(points, np.float64), np.asarray(colors, np.uint8), vals
    origin = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
    rel = np.asarray(points, np.float64) - origin
    keys = voxel_keys(points, voxel, origin)
    _, inv, cnt = np.unique(_flat_keys(keys), return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    m = len(cnt)
    cols = np.asarray(colors, np.float64)
    P = np.stack([np.bincount(inv, weights=rel[:, i], minlength=m) for i in range(3)], 1) / cnt[:, None]
    C = np.stack([np.bincount(inv, weights=cols[:, i], minlength=m) for i in range(3)], 1) / cnt[:, None]
    V = None
    if vals is not None:
        V = np.bincount(inv, weights=vals, minlength=m) / cnt
    return P + origin, np.clip(C.round(), 0, 255).astype(np.uint8), V


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray, confidence: np.ndarray | None = None) -> None:
    """Coloured point cloud as binary PLY (trimesh), written atomically.

    Positions are stored as float32 (the PLY exporter's type). With
    ``confidence`` (N,) each vertex also gets a float ``confidence`` property
    (see :class:`init.InitResult`); readers that do not know it ignore it.
    """
    import trimesh

    from .fileio import atomic_path

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    col = np.asarray(colors, np.uint8).reshape(-1, 3)
    rgba = np.concatenate([col, np.full((len(col), 1), 255, np.uint8)], 1)
    if confidence is None:
        obj = trimesh.PointCloud(pts, colors=rgba)
    else:
        conf = np.asarray(confidence, np.float32).reshape(-1)
        if len(conf) != len(pts):
            raise ValueError(f"write_ply: {len(conf)} confidences for {len(pts)} points")
        # A face-less mesh: trimesh's PLY exporter writes vertex attributes for meshes, not point clouds.
        obj = trimesh.Trimesh(vertices=pts, faces=np.zeros((0, 3), np.int64), vertex_colors=rgba, process=False)
        obj.vertex_attributes["confidence"] = conf
    with atomic_path(path) as tmp:
        obj.export(tmp, file_type="ply")


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(points (N,3) float64, colors (N,3) uint8) of a PLY written by :func:`write_ply`."""
    import trimesh

    pc = trimesh.load(path, process=False)
    pts = np.asarray(pc.vertices, np.float64)
    cols = getattr(pc, "colors", None)
    if cols is None or len(cols) != len(pts):
        cols = np.full((len(pts), 3), 128, np.uint8)
    return pts, np.asarray(cols)[:, :3].astype(np.uint8)


def read_ply_confidence(path: str | Path) -> np.ndarray | None:
    """The per-vertex ``confidence`` (N,) float64 of a PLY written by :func:`write_ply`, or None without one."""
    import trimesh

    pc = trimesh.load(path, process=False)
    data = pc.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    names = getattr(getattr(data, "dtype", None), "names", None) or ()
    if "confidence" not in names:
        return None
    return np.asarray(data["confidence"], np.float64).reshape(-1)
