"""What the geometry stages share: the training cameras and images, the up frame, a local origin
and the scene's scale (scene units per paper unit), with the scale taken from the SfM points
when the cameras' axes do not converge (a mapping grid).

The scale is the width of ground a view covers, against LEVIR-NVS's: the reference distance times
the lens's span (:func:`~dibrgs_core.camera.frame.span_factor`), over 115. A satellite's narrow view
from 20 km covers what a drone's covers from 200 m, and gets the same thresholds."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..camera.frame import estimate_up, nadir_angle_deg, overlap_distance, span_factor, up_frame
from ..camera.pinhole import Camera
from ..common.errors import InputError
from ..data.images import fill_no_data
from ..common.report import Report
from .config import LEVIR_REFERENCE_DEPTH, STAGE, InitConfig
from .sfm import SparseCloud
from .mvs import area_resize
from .sweep_range import converging_target


@dataclass
class SceneGeometry:
    """What the stages share: training cameras and images, the up frame and the scale."""

    cameras: list[Camera]
    images: list[np.ndarray]
    gt_depths: list[np.ndarray | None]
    up: np.ndarray
    up_confidence: float
    frame: np.ndarray
    origin: np.ndarray
    nadir_deg: float
    scale: float
    ref_distance: float
    ref_source: str = "look-at"
    span: float = 1.0  # the lens's span against the reference lens (camera.frame.span_factor)
    resize: float = 1.0  # the training photos' size factor here (InitConfig.max_side)
    #: per view, bool (H, W) pixels that hold data (their images are 0 elsewhere), None when all do
    valid: list[np.ndarray | None] | None = None

    def __post_init__(self) -> None:
        if self.valid is None:
            self.valid = [None] * len(self.cameras)

    @property
    def n_pixels(self) -> int:
        return int(sum(c.width * c.height for c in self.cameras))


def scene_geometry(scene: Any, config: InitConfig) -> SceneGeometry:
    """Cameras, up frame, local origin and scale of the scene's training views.

    The reference distance (the scale's numerator) is the median distance from
    the cameras to the point their axes converge on when they converge
    (:func:`mvs.converging_target`: orbits). Nearly parallel axes (a nadir
    mapping grid) meet nowhere in particular, so there it is provisional: the
    cameras' depth ranges, else a guess from their spacing
    (:func:`~dibrgs_core.camera.frame.overlap_distance`), until :func:`sfm_reference` replaces it with
    the depth of the SfM points. ``ref_source`` says which.
    """
    views = list(scene.train_views())
    if not views:
        raise InputError(getattr(scene, "root", None), "the scene has no training views")
    side = max(max(v.camera.width, v.camera.height) for v in views)
    resize = config.max_side / side if 0 < config.max_side < side else 1.0
    cams = [v.camera.scaled(resize) if resize != 1.0 else v.camera for v in views]
    up, conf = estimate_up(cams)
    centers = np.stack([c.center for c in cams])
    target = converging_target(cams)
    ranges = [c.depth_range for c in cams if c.depth_range and 0 < c.depth_range[0] < c.depth_range[1]]
    if target is not None:
        ref, source = float(np.median(np.linalg.norm(centers - target, axis=1))), "look-at"
        origin = target
    else:
        if ranges:
            ref, source = float(np.median([np.sqrt(a * b) for a, b in ranges])), "depth-range"
        else:
            ref, source = overlap_distance(cams), "camera-spacing"
        # A point ``ref`` in front of the cameras' centroid: the ground below them, roughly.
        origin = centers.mean(0) + ref * np.mean([c.view_dir for c in cams], axis=0)
    span = span_factor(cams)
    scale = float(config.scale) if config.scale else ref * span / LEVIR_REFERENCE_DEPTH
    images, valid = [], []
    for v, c in zip(views, cams):
        image, ok = v.pixels()
        if resize != 1.0:  # a pixel drawn from any pixel without data has none
            image = area_resize(fill_no_data(np.asarray(image, np.float32), ok, np.nan), c)
            ok = None if ok is None else np.isfinite(image).all(axis=2)
        images.append(np.nan_to_num(np.asarray(image, np.float32)))
        valid.append(ok)
    depths = [v.depth if resize == 1.0 or v.depth is None else _nearest(v.depth, c) for v, c in zip(views, cams)]
    return SceneGeometry(cams, images, depths, up, float(conf), up_frame(up), origin, nadir_angle_deg(cams, up), scale,
                         ref, source, span, resize, valid)


def _nearest(depth: np.ndarray, cam: Camera) -> np.ndarray:
    """``depth`` (H, W) sampled at the pixel centres of the smaller ``cam`` (no mixing across edges)."""
    H, W = depth.shape
    rows = np.minimum(((np.arange(cam.height) + 0.5) * H / cam.height).astype(np.int64), H - 1)
    cols = np.minimum(((np.arange(cam.width) + 0.5) * W / cam.width).astype(np.int64), W - 1)
    return np.ascontiguousarray(depth[rows][:, cols])


def sfm_reference(geo: SceneGeometry, sparse: SparseCloud, config: InitConfig, report: Report) -> None:
    """Replace a provisional reference distance (see :func:`scene_geometry`) by the median z-depth of the
    SfM points in the training views, and the origin by their median; the scale follows (unless
    ``config.scale`` is set)."""
    def decide(why: str) -> None:
        lens = "" if abs(geo.span - 1.0) < 0.01 else f"; the lens covers {geo.span:.3g} x the reference's width"
        given = f"; scale {config.scale:g} as given" if config.scale else ""
        report.decide(STAGE, "scene_scale", True, f"{why}{lens}{given}", source=geo.ref_source,
                      ref_distance=geo.ref_distance, span=geo.span, scale=geo.scale)

    if geo.ref_source == "look-at" or len(sparse) < config.min_sfm_points:
        decide(f"reference distance {geo.ref_distance:.4g} from the "
               f"{'point the cameras converge on' if geo.ref_source == 'look-at' else geo.ref_source}")
        return
    depths = []
    for c in geo.cameras:
        uv, z = c.project(sparse.points)
        ok = c.in_image(uv, z)
        depths.append(z[ok])
    z = np.concatenate(depths)
    if len(z) < config.min_sfm_points:
        decide(f"reference distance {geo.ref_distance:.4g} from the {geo.ref_source}: only {len(z)} SfM points "
               "in the views")
        return
    old, old_source = geo.ref_distance, geo.ref_source
    geo.ref_distance = float(np.median(z))
    geo.origin = np.median(sparse.points, axis=0)
    geo.ref_source = "sfm"
    if not config.scale:
        geo.scale = geo.ref_distance * geo.span / LEVIR_REFERENCE_DEPTH
    decide(f"the cameras' axes do not converge (parallel views): reference distance {geo.ref_distance:.4g} = "
           f"median SfM point depth (provisional {old:.4g} from the {old_source})")
