"""Coloured point clouds as PLY files (trimesh): positions float64 in world units, colours uint8 RGB."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..common.fileio import atomic_path


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray, confidence: np.ndarray | None = None) -> None:
    """Coloured point cloud as binary PLY (trimesh), written atomically.

    Positions are stored as float32 (the PLY exporter's type). With
    ``confidence`` (N,) each vertex also gets a float ``confidence`` property
    (see :class:`~dibrgs_core.geometry.pipeline.InitResult`); readers that do not know it ignore it.
    """
    import trimesh

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
