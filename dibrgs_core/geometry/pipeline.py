"""Geometry initialisation: sparse SfM, an aligned dense depth prior (completed where it failed),
an overlap-free fused cloud with per-point confidence, the height map.

Paper sections "Initialization with Dense Depth Priors", "Height-constrained Anchor Growth" and
"Implementation Details". Every step decides from the scene whether it applies and records the
decision in the report. Options and units: :mod:`.config`.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..camera.frame import near_nadir
from ..common.errors import InputError
from ..common.report import Report
from ..data.ply import read_ply, write_ply
from ..data.scene import Scene, origin_decision
from .completion import complete_depths, measured_confidence
from .config import STAGE, InitConfig
from .depth_prior import MAPS, Alignment, align_view, compute_prior, map_disparity
from .fusion import (
    backproject_views,
    dip_cells,
    neighbour_pairs_estimate,
    overlap_pairs_drop,
    reproject_max_depth,
    to_frame,
)
from .height_map import HeightMap
from .pointcloud import voxel_confident
from .scene_geometry import SceneGeometry, scene_geometry, sfm_reference
from .sfm import SparseCloud, triangulate_known_poses

log = logging.getLogger("dibrgs.init")

#: Folder of ``WORK/init`` where the plane sweep keeps each view's depth as it finishes (resume).
SWEEPS = "sweeps"


@dataclass
class InitResult:
    """Initial point cloud (world float64, uint8 colours), height map (or None) and report.

    ``confidence`` (N,) in [0, 1] says how each point was obtained: 1 for SfM
    points; ``0.5 + 0.5 c`` for depth the prior measured (``c`` is the plane
    sweep's per-pixel confidence, 1 for a prior without one); below 0.5
    (``InitConfig.completion_confidence``) for depth completed from the height
    field; 0 for the plane fallback. ``points.ply`` stores it as a vertex
    property (:func:`fusion.read_ply_confidence`). ``dense_points`` /
    ``dense_confidence`` are the fused cloud before voxel downsampling (what the
    evaluation reprojects).
    """

    points: np.ndarray
    colors: np.ndarray
    height_map: HeightMap | None
    report: Report
    confidence: np.ndarray | None = None
    dense_points: np.ndarray | None = None
    dense_confidence: np.ndarray | None = None


def run_sparse(geo: SceneGeometry, config: InitConfig, report: Report) -> SparseCloud:
    """SfM with the poses fixed; an empty cloud (with the reason) when it finds too few points."""
    t = time.time()
    try:
        sparse = triangulate_known_poses(geo.cameras, geo.images, origin=geo.origin, config=config.sfm, valid=geo.valid)
    except Exception as e:  # pycolmap failures must not stop initialisation
        log.warning("SfM failed: %s", e)
        sparse = SparseCloud.empty()
        report.values["sfm_error"] = str(e)
    report.values["sfm_s"] = time.time() - t
    report.values["sfm_points"] = len(sparse)
    ok = len(sparse) >= config.min_sfm_points
    report.decide(STAGE, "sfm", ok, f"{len(sparse)} SfM points" + ("" if ok else
                  f" < {config.min_sfm_points}: not used; depth ranges and scales come from the cameras"),
                  points=len(sparse), mean_track=float(sparse.track_lengths.mean()) if len(sparse) else 0.0)
    return sparse if ok else SparseCloud.empty()


def prior_depths(geo: SceneGeometry, config: InitConfig, sparse_points: np.ndarray, report: Report,
                 depth_map: str | None = None, prior=None) -> list[np.ndarray]:
    """Dense metric depth per training view from the configured prior, aligned to ``sparse_points``.

    ``prior`` lets a caller pass precomputed :class:`PriorMaps` (the evaluation reuses them).
    """
    name = config.depth_prior
    if name == "auto":
        name = "depth-anything-v2" if config.depth_model else "mvs"
    mode = depth_map or config.depth_map
    if mode not in MAPS:
        raise InputError(None, f"unknown --map {mode!r} (use one of {MAPS})")
    if prior is None:
        t = time.time()
        prior = compute_prior(name, geo.cameras, geo.images, geo.gt_depths, sparse_points, geo.ref_distance,
                              config.depth_model, config.mvs, valid=geo.valid)
        report.values["prior_s"] = time.time() - t
    report.values["prior"] = name
    out = []
    aligns: list[dict] = []
    for cam, raw in zip(geo.cameras, prior.maps):
        raw = np.asarray(raw, np.float64)
        if prior.kind == "depth":
            al = align_view(cam, raw, sparse_points, "depth", geo.ref_distance)
            aligns.append(asdict(al))
            # A metric prior is not rescaled; the fit (a ~ 1, b ~ 0 expected) is kept as a check.
            out.append(np.where(np.isfinite(raw) & (raw > 0), raw, np.nan))
        else:
            pseudo = map_disparity(raw, mode)
            al: Alignment = align_view(cam, pseudo, sparse_points, mode, geo.ref_distance)
            aligns.append(asdict(al))
            if al.reason:
                report.decide(STAGE, f"align[{cam.name}]", al.method == "robust-lsq", al.reason, a=al.a, b=al.b)
            out.append(al.apply(pseudo))
    report.values["alignment"] = aligns
    # no depth where a photo holds no data, whatever the prior made of its fill
    out = [d if v is None else np.where(v, d, np.nan) for d, v in zip(out, geo.valid)]
    if prior.kind == "depth":
        report.decide(STAGE, "align", False, f"the {name} prior is metric depth; the affine fit against SfM is "
                      "recorded as a check only", fits=[(a["a"], a["b"], a["n_points"]) for a in aligns])
    else:
        report.decide(STAGE, "align", True, f"{mode} map, robust least squares against SfM depths",
                      fits=[(a["a"], a["b"], a["n_points"]) for a in aligns])
    return out


def overlap_applicable(geo: SceneGeometry, config: InitConfig) -> tuple[bool, str]:
    """Overlap removal and the height map need near-nadir cameras and a clear up axis."""
    return near_nadir(geo.cameras, config.max_nadir_deg, config.min_up_confidence)


def refine_cloud(geo: SceneGeometry, config: InitConfig, depths: list[np.ndarray], refine: str, report: Report,
                 confidence: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse the views' depths with the chosen refinement.

    Returns the dense (points, colors, confidence), not downsampled (but thinned
    at random before the overlap removal when many views measured the same ground:
    ``config.max_overlap_pairs``); the confidence of a point is its pixel's in
    ``confidence`` (HxW maps, one per view; 1 everywhere when None).
    """
    if refine == "reproject":
        depths = reproject_max_depth(geo.cameras, depths)
    pts, cols, _ = backproject_views(geo.cameras, depths, geo.images)
    conf = _pixel_values(depths, confidence)
    report.values["dense_points"] = len(pts)
    if refine != "no-ovlp":
        report.decide(STAGE, "overlap_removal", False, f"refinement '{refine}' chosen")
        return pts, cols, conf
    ok, why = overlap_applicable(geo, config)
    if not report.decide(STAGE, "overlap_removal", ok, why):
        return pts, cols, conf
    s = geo.scale
    local = to_frame(pts, geo.frame, geo.origin)
    pairs = neighbour_pairs_estimate(local[:, :2], config.eps_xy * s)
    keep_share = min(1.0, math.sqrt(config.max_overlap_pairs / max(pairs, 1.0)))
    report.values["overlap_pairs_estimate"] = pairs
    if report.decide(STAGE, "thinning", keep_share < 1.0,
                     f"{len(pts)} points, about {pairs / 1e6:,.1f} million pairs closer than eps_xy "
                     + (f"> {config.max_overlap_pairs / 1e6:g} million: a random {100 * keep_share:.3g} % kept "
                        "(many views measured the same ground)" if keep_share < 1.0 else
                        f"<= {config.max_overlap_pairs / 1e6:g} million")):
        keep = np.random.default_rng(0).random(len(pts)) < keep_share
        pts, cols, conf, local = pts[keep], cols[keep], conf[keep], local[keep]
        report.values["dense_points_thinned"] = len(pts)
    t = time.time()
    dip = dip_cells(local, config.dip_cell * s, config.dip_alpha, config.dip_min_points)
    report.values["dip_s"] = time.time() - t
    report.decide(STAGE, "dip_test", dip.n_multimodal > 0,
                  f"{dip.n_multimodal} of {dip.n_tested} tested cells multimodal (p < {config.dip_alpha})"
                  + ("" if dip.n_multimodal else ": no overlap to remove"),
                  cells=dip.n_cells, tested=dip.n_tested, multimodal=dip.n_multimodal)
    if dip.n_multimodal == 0:
        return pts, cols, conf
    drop = overlap_pairs_drop(local, dip.in_multimodal, config.dip_cell * s, config.eps_xy * s, config.eps_z * s)
    report.values["overlap_dropped"] = int(drop.sum())
    log.info("overlap removal: dropped %d of %d points", drop.sum(), len(pts))
    return pts[~drop], cols[~drop], conf[~drop]


def _pixel_values(depths: list[np.ndarray], maps: list[np.ndarray] | None) -> np.ndarray:
    """Per back-projected point (the order of :func:`fusion.backproject_views`), its pixel's value in ``maps``."""
    out = []
    for i, d in enumerate(depths):
        d = np.asarray(d, np.float64).reshape(-1)
        ok = np.isfinite(d) & (d > 0)
        out.append(np.ones(int(ok.sum())) if maps is None else np.asarray(maps[i], np.float64).reshape(-1)[ok])
    return np.concatenate(out) if out else np.zeros(0)


def initialise(scene: Any, out_dir: str | Path, config: InitConfig | None = None) -> InitResult:
    """Run the whole initialisation and write ``points.ply``, ``height_map.npz`` and ``init_report.json``."""
    cfg = config or InitConfig()
    out = Path(out_dir)
    report = Report()
    t0 = time.time()
    geo = scene_geometry(scene, cfg)
    report.values.update(up=geo.up, up_confidence=geo.up_confidence, nadir_deg=geo.nadir_deg, config=_config_dict(cfg),
                         inputs=init_inputs(scene, cfg), train=[c.name for c in geo.cameras],
                         # where the files' frame has the points' (0, 0, 0) (Scene.origin; the add-on places them)
                         scene_origin=[float(v) for v in getattr(scene, "origin", (0.0, 0.0, 0.0))])
    if isinstance(scene, Scene):
        report.decide(STAGE, "recentre", *origin_decision(scene))
    c = geo.cameras[0]
    if geo.resize != 1.0:
        why = (f"training photos worked on at {c.width}x{c.height} (x{geo.resize:.4g}; long side {cfg.max_side} px: "
               "their finer detail is below the dense cloud's voxel)")
    elif cfg.max_side:
        why = f"training photos of {c.width}x{c.height} are within the {cfg.max_side} px working size"
    else:
        why = "training photos at their own size (max_side 0)"
    report.decide(STAGE, "working_size", geo.resize != 1.0, why)
    sparse = run_sparse(geo, cfg, report)
    sfm_reference(geo, sparse, cfg, report)
    report.values.update(scale=geo.scale, origin=geo.origin, ref_distance=geo.ref_distance, ref_source=geo.ref_source,
                         span=geo.span)
    density = len(sparse) / max(geo.n_pixels, 1)
    use_prior = density < cfg.dense_sfm_ratio
    report.decide(STAGE, "depth_prior", use_prior,
                  f"SfM gives {density:.4f} points per training pixel "
                  + (f"< {cfg.dense_sfm_ratio}: densify with a prior" if use_prior else f">= {cfg.dense_sfm_ratio}: already dense"))
    pts, cols, conf = np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0)
    if use_prior:
        name = cfg.depth_prior if cfg.depth_prior != "auto" else ("depth-anything-v2" if cfg.depth_model else "mvs")
        t = time.time()
        prior = compute_prior(name, geo.cameras, geo.images, geo.gt_depths, sparse.points, geo.ref_distance,
                              cfg.depth_model, cfg.mvs, checkpoint=out / SWEEPS, valid=geo.valid)
        report.values["prior_s"] = time.time() - t
        depths = prior_depths(geo, cfg, sparse.points, report, prior=prior)
        confs = [measured_confidence(None if prior.confidence is None else prior.confidence[i], d.shape)
                 for i, d in enumerate(depths)]
        _record_coverage(geo, depths, report)
        depths, confs = complete_depths(geo, cfg, depths, confs, sparse.points, report)
        pts, cols, conf = refine_cloud(geo, cfg, depths, cfg.refine, report, confs)
    dense_pts, dense_conf = pts, conf
    if len(pts):
        pts, cols, conf = voxel_confident(pts, cols, conf, cfg.voxel * geo.scale, geo.origin,
                                          completed_factor=cfg.completion_voxel)
    report.values["voxel_points"] = len(pts)
    pts = np.concatenate([pts, sparse.points])
    cols = np.concatenate([cols, sparse.colors])
    conf = np.concatenate([conf, np.ones(len(sparse))])  # triangulated: measured
    if len(pts) == 0:
        # Nothing triangulated nor matched: a plane through the look-at point keeps training possible.
        pts, cols = _plane_fallback(geo)
        conf = np.zeros(len(pts))  # a guess, not a measurement
        dense_pts, dense_conf = pts, conf
        report.decide(STAGE, "plane_fallback", True, "no SfM points and no prior depth: a plane at the cameras' "
                      "look-at point stands in for the scene")
    finite = np.isfinite(pts).all(1)
    pts, cols, conf = pts[finite], cols[finite], conf[finite]
    report.values["points"] = len(pts)
    report.values["points_completed"] = int((conf < 0.5).sum())

    hm = None
    ok, why = overlap_applicable(geo, cfg)
    if report.decide(STAGE, "height_map", ok, why):
        src = np.concatenate([dense_pts, sparse.points]) if len(dense_pts) else pts
        hm = HeightMap.build(src, geo.frame, geo.origin, cfg.height_cell * geo.scale, cfg.height_percentile,
                             cfg.height_relax, cfg.height_margin * geo.scale)
    report.values["init_s"] = time.time() - t0 - float(report.values.get("model_load_s", 0.0))

    write_ply(out / "points.ply", pts, cols, conf)
    hm_path = out / "height_map.npz"
    if hm is not None:
        hm.save(hm_path)
    elif hm_path.exists():
        hm_path.unlink()  # a stale map from an earlier run must not be picked up
    report.save(out / "init_report.json")
    return InitResult(pts, cols, hm, report, conf, dense_pts, dense_conf)


def _record_coverage(geo: SceneGeometry, depths: list[np.ndarray], report: Report) -> None:
    """Share of each training view's pixels the prior gave a depth (report value ``prior_coverage``)."""
    cov = {c.name: float((np.isfinite(d) & (np.asarray(d) > 0)).mean()) for c, d in zip(geo.cameras, depths)}
    report.values["prior_coverage"] = cov
    log.info("prior depth on %s of the training pixels", ", ".join(f"{100 * v:.1f} %" for v in cov.values()))


def init_inputs(scene: Any, config: InitConfig) -> str:
    """Digest of what an initialisation reads from the scene: its training views' names, cameras
    and images, and their depth maps when the prior is the oracle (``gt``)."""
    from ..data.scene import views_digest

    return views_digest(scene.train_views(), depth=config.depth_prior == "gt")


def load_result(out_dir: str | Path, config: InitConfig, inputs: str | None = None) -> InitResult | None:
    """The result :func:`initialise` saved in ``out_dir``, or None when there is none, it is
    unreadable, or it was made from other inputs (``inputs``: :func:`init_inputs` of the scene; an
    initialisation that does not record its inputs is never reused) or with another depth prior or
    depth model. Other options (voxel, refinement) are those ``dibrgs init`` was given."""
    import json

    out = Path(out_dir)
    rep_path, ply = out / "init_report.json", out / "points.ply"
    if not (rep_path.exists() and ply.exists()):
        return None
    try:
        report = Report.from_dict(json.loads(rep_path.read_text()))
    except (OSError, ValueError, TypeError) as e:
        log.warning("%s unreadable (%s); initialising again", rep_path, e)
        return None
    old = report.values.get("config", {})
    # The prior first: the oracle's inputs hold the depth maps, so a change of prior changes them too.
    if old.get("depth_prior") != config.depth_prior or old.get("depth_model") != config.depth_model:
        log.info("%s was made with another depth prior; initialising again", out)
        return None
    if inputs is not None and report.values.get("inputs") != inputs:
        log.info("%s was made from other training views; initialising again", out)
        return None
    try:
        pts, cols = read_ply(ply)
        hm = HeightMap.load(out / "height_map.npz") if (out / "height_map.npz").exists() else None
    except Exception as e:  # a damaged cache is rebuilt, never fatal
        log.warning("%s: cached initialisation unreadable (%s); initialising again", out, e)
        return None
    log.info("reusing the geometry initialisation in %s (same training views and prior)", out)
    return InitResult(pts, cols, hm, report)


def _plane_fallback(geo: SceneGeometry, n: int = 32) -> tuple[np.ndarray, np.ndarray]:
    F = geo.frame
    half = geo.ref_distance * geo.span * 0.5
    g = np.linspace(-half, half, n)
    a, b = np.meshgrid(g, g)
    P = geo.origin + a.reshape(-1, 1) * F[0] + b.reshape(-1, 1) * F[1]
    return P, np.full((len(P), 3), 128, np.uint8)


def _config_dict(cfg: InitConfig) -> dict:
    d = asdict(cfg)
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in d.items()}
