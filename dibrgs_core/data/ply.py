"""Coloured point clouds as PLY files (trimesh): positions float64 in world units, colours uint8 RGB."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..common.fileio import atomic_path


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray) -> None:
    """Coloured point cloud as binary PLY (trimesh), written atomically. Positions are float64 world."""
    import trimesh

    pts = np.asarray(points, np.float64).reshape(-1, 3)
    col = np.asarray(colors, np.uint8).reshape(-1, 3)
    rgba = np.concatenate([col, np.full((len(col), 1), 255, np.uint8)], 1)
    pc = trimesh.PointCloud(pts, colors=rgba)
    with atomic_path(path) as tmp:
        pc.export(tmp, file_type="ply")


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(points (N,3) float64, colors (N,3) uint8) of a PLY written by :func:`write_ply`."""
    import trimesh

    pc = trimesh.load(path, process=False)
    pts = np.asarray(pc.vertices, np.float64)
    cols = getattr(pc, "colors", None)
    if cols is None or len(cols) != len(pts):
        cols = np.full((len(pts), 3), 128, np.uint8)
    return pts, np.asarray(cols)[:, :3].astype(np.uint8)
