"""Completing the dense depth where matching failed (near-nadir scenes): a 2.5D surface of what
was measured, rendered into the training pixels without depth, at a lower confidence.

Depth is z-depth in world units (0 / non-finite = none); confidences in [0, 1], measured depth
at 0.5 and above, completed depth below.
"""
from __future__ import annotations

import time

import numpy as np

from ..camera.frame import near_nadir
from ..camera.pinhole import Camera
from ..common.report import Report
from .config import STAGE, InitConfig
from .fusion import backproject_views, to_frame
from .height_map import completion_field
from .scene_geometry import SceneGeometry


def measured_confidence(prior_confidence: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """Point confidence of measured depth: ``0.5 + 0.5 c`` for the prior's per-pixel confidence ``c`` in
    [0, 1] (plane sweep: its peak ratio), 1 for a prior without one. Completed depth stays below 0.5."""
    if prior_confidence is None:
        return np.ones(shape)
    c = np.nan_to_num(np.asarray(prior_confidence, np.float64), nan=0.0)
    return 0.5 + 0.5 * np.clip(c, 0.0, 1.0)


def complete_depths(geo: SceneGeometry, config: InitConfig, depths: list[np.ndarray], confidence: list[np.ndarray],
                    sparse_points: np.ndarray, report: Report) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Fill the pixels the prior left without depth from a 2.5D surface of what it measured (near-nadir scenes).

    The SfM points and the measured depths become a height field
    (:func:`height_map.completion_field`: the median height per cell of
    ``config.completion_cell_px`` pixels, the ground's low percentile and
    slope where nothing was measured, reaching over the training views'
    footprints); each training pixel without depth gets the depth at which its
    ray meets that surface, with confidence ``config.completion_confidence``
    (below every measured point's). Skipped, with the reason in the report,
    when the scene is not near-nadir (``auto``), when ``config.complete`` is
    ``off``, or with too few measured points. Pixels without data stay without depth.
    """
    holes = sum(int((~(np.isfinite(d) & (np.asarray(d) > 0))).sum()) for d in depths)
    if config.complete == "off":
        report.decide(STAGE, "completion", False, "switched off")
        return depths, confidence
    ok, why = near_nadir(geo.cameras, config.max_nadir_deg, config.min_up_confidence)
    if not ok and config.complete == "auto":
        report.decide(STAGE, "completion", False, f"a height field does not describe this scene: {why}")
        return depths, confidence
    if holes == 0:
        report.decide(STAGE, "completion", False, "every training pixel already has a depth")
        return depths, confidence
    pts, _, _ = backproject_views(geo.cameras, depths, [np.zeros((c.height, c.width, 3)) for c in geo.cameras])
    pts = np.concatenate([pts, np.asarray(sparse_points, np.float64).reshape(-1, 3)])
    if len(pts) < config.min_sfm_points:
        report.decide(STAGE, "completion", False, f"only {len(pts)} measured points to build a surface from")
        return depths, confidence
    t = time.time()
    f = float(np.median([0.5 * (c.fx + c.fy) for c in geo.cameras]))
    cell = config.completion_cell_px * geo.ref_distance / f
    ground = float(np.median(to_frame(pts, geo.frame, geo.origin)[:, 2]))
    field = completion_field(pts, geo.frame, geo.origin, cell, _footprints(geo, ground))
    out_d, out_c, filled = [], [], 0
    for cam, d, c, has_data in zip(geo.cameras, depths, confidence, geo.valid):
        d = np.asarray(d, np.float64)
        hole = ~(np.isfinite(d) & (d > 0))
        if has_data is not None:  # no data: nothing to place
            hole &= has_data
        surf = _surface_depth(field, cam, config.mvs.max_size) if hole.any() else np.zeros_like(d)
        fill = hole & (surf > 0)
        filled += int(fill.sum())
        out_d.append(np.where(fill, surf, d))
        out_c.append(np.where(fill, config.completion_confidence, c))
    report.values["completion_s"] = time.time() - t
    n_pix = geo.n_pixels
    report.decide(STAGE, "completion", True,
                  f"{why if ok else 'switched on'}: {100.0 * filled / n_pix:.1f} % of the training pixels completed from a height field of "
                  f"{len(pts)} measured points ({100.0 * (n_pix - holes) / n_pix:.1f} % measured), confidence "
                  f"{config.completion_confidence}", measured=(n_pix - holes) / n_pix, completed=filled / n_pix,
                  cell=field.cell)
    return out_d, out_c


def _surface_depth(field, cam: Camera, max_size: int) -> np.ndarray:
    """Depth (H,W) float64 of ``field`` seen by ``cam`` (0 = no surface), rendered at most ``max_size``
    pixels on the long side and upsampled: the surface is coarser than that."""
    import torch
    import torch.nn.functional as F

    longest = max(cam.width, cam.height)
    if not max_size or longest <= max_size:
        return field.depth(cam).astype(np.float64)
    small = cam.scaled(max_size / longest)
    d = torch.from_numpy(field.depth(small).astype(np.float64))[None, None]
    valid = (d > 0).double()
    size = (cam.height, cam.width)
    lin = F.interpolate(d, size=size, mode="bilinear", align_corners=False)[0, 0]
    full = F.interpolate(valid, size=size, mode="bilinear", align_corners=False)[0, 0]
    near = F.interpolate(d, size=size, mode="nearest-exact")[0, 0]
    # Bilinear where all four neighbours hit the surface, nearest along its edge.
    return torch.where(full > 1 - 1e-9, lin, near).numpy()


def _footprints(geo: SceneGeometry, height: float) -> np.ndarray:
    """Local horizontal (e1, e2) points where the training views' image borders meet the plane at local
    ``height`` (rays that do not descend are left out)."""
    out = []
    for c in geo.cameras:
        u = np.linspace(0, c.width, 9)
        v = np.linspace(0, c.height, 9)
        border = np.concatenate([np.stack([u, np.zeros_like(u)], 1), np.stack([u, np.full_like(u, c.height)], 1),
                                 np.stack([np.zeros_like(v), v], 1), np.stack([np.full_like(v, c.width), v], 1)])
        rays = np.c_[border, np.ones(len(border))] @ np.linalg.inv(c.K).T @ c.R  # world, camera-z 1
        dl = rays @ geo.frame.T
        cl = geo.frame @ (c.center - geo.origin)
        down = dl[:, 2] < -1e-12 * np.linalg.norm(dl, axis=1)
        t = (height - cl[2]) / np.where(down, dl[:, 2], -1.0)
        ok = down & (t > 0)
        out.append(cl[:2] + t[ok, None] * dl[ok, :2])
    return np.concatenate(out) if out else np.zeros((0, 2))
