"""Geometry initialisation: sparse SfM, an aligned dense depth prior, an overlap-free fused cloud, the height map.

Paper sections "Initialization with Dense Depth Priors", "Height-constrained
Anchor Growth" and "Implementation Details". Every step decides from the
scene whether it applies and records the decision in the report.

Units. The paper's thresholds (eps_xy 0.1, eps_z 1.0, voxel 1.0, height-map
cell 10) are in LEVIR-NVS units, where the training cameras are about
``LEVIR_REFERENCE_DEPTH`` = 115 units from the scene (the paper's MAE / Abs
Rel ratio, 3.16 / 0.0273). ``InitConfig.scale = None`` scales them by
``median camera-to-look-at distance / 115`` so a scene in other units (or a
generated one) gets the same relative thresholds; a number overrides it.
"""
from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..camera.pinhole import Camera
from ..camera.frame import MAX_NADIR_DEG, MIN_UP_CONFIDENCE, estimate_up, look_at_target, nadir_angle_deg, near_nadir, up_frame
from .depth_prior import MAPS, Alignment, align_view, compute_prior, map_disparity
from ..common.errors import InputError
from ..common.modes import DepthMap, DepthPrior, Refine
from .fusion import backproject_views, dip_cells, overlap_pairs_drop, reproject_max_depth, to_frame
from .pointcloud import voxel_downsample
from ..data.ply import read_ply, write_ply
from .height_map import HeightMap
from .mvs import MvsConfig
from ..common.report import Report
from .sfm import SfmConfig, SparseCloud, triangulate_known_poses

log = logging.getLogger("dibrgs.init")

LEVIR_REFERENCE_DEPTH = 115.0
STAGE = "init"


@dataclass
class InitConfig:
    """Initialisation options; lengths are in paper (LEVIR-NVS) units, multiplied by the scene scale.

    Attributes:
        depth_prior: ``auto`` (depth-anything-v2 when ``depth_model`` is given, else ``mvs``),
            ``mvs``, ``depth-anything-v2`` or ``gt``.
        depth_model: local folder of Depth Anything V2 weights.
        depth_map: ``inv`` (depth = 1/disparity, the paper's choice) or ``neg``.
        refine: ``no-ovlp`` (ours), ``reproject`` or ``none``.
        scale: world units per paper unit; None = auto (see module docstring).
        dip_cell: side of the dip-test cells.
        dip_alpha: significance of the dip test (p < alpha = multimodal).
        dip_min_points: cells with fewer points are not tested.
        eps_xy, eps_z: overlap thresholds (horizontal, vertical).
        voxel: voxel-downsampling size (0 disables).
        height_cell: height-map cell size.
        height_percentile: per-cell height percentile.
        height_relax: factor on the height above ground (see height_map).
        height_margin: added to every bound.
        max_nadir_deg: mean view direction farther than this from straight down = not near-nadir.
        min_up_confidence: ``estimate_up`` confidence below this = ambiguous up axis.
        min_sfm_points: fewer SfM points = SfM is not usable for alignment/ranges.
        dense_sfm_ratio: SfM points per training pixel at or above which the cloud
            already counts as dense and no depth prior is run.
    """

    depth_prior: DepthPrior = "auto"
    depth_model: str | None = None
    depth_map: DepthMap = "inv"
    refine: Refine = "no-ovlp"
    scale: float | None = None
    dip_cell: float = 2.0
    dip_alpha: float = 0.05
    dip_min_points: int = 8
    eps_xy: float = 0.1
    eps_z: float = 1.0
    voxel: float = 1.0
    height_cell: float = 10.0
    height_percentile: float = 95.0
    height_relax: float = 1.1
    height_margin: float = 1.0
    max_nadir_deg: float = MAX_NADIR_DEG
    min_up_confidence: float = MIN_UP_CONFIDENCE
    min_sfm_points: int = 20
    dense_sfm_ratio: float = 0.05
    sfm: SfmConfig = field(default_factory=SfmConfig)
    mvs: MvsConfig = field(default_factory=MvsConfig)


@dataclass
class InitResult:
    """Initial point cloud (world float64, uint8 colours), height map (or None) and report."""

    points: np.ndarray
    colors: np.ndarray
    height_map: HeightMap | None
    report: Report


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

    @property
    def n_pixels(self) -> int:
        return int(sum(c.width * c.height for c in self.cameras))


def scene_geometry(scene: Any, config: InitConfig) -> SceneGeometry:
    """Cameras, up frame, local origin and scale of the scene's training views."""
    views = list(scene.train_views())
    if not views:
        raise InputError(getattr(scene, "root", None), "the scene has no training views")
    cams = [v.camera for v in views]
    up, conf = estimate_up(cams)
    target = look_at_target(cams)
    centers = np.stack([c.center for c in cams])
    dist = np.linalg.norm(centers - target, axis=1)
    if not np.all(np.isfinite(dist)) or np.median(dist) <= 0:
        dist = np.array([np.mean(c.depth_range) if c.depth_range else 1.0 for c in cams])
    ref = float(np.median(dist))
    origin = target if np.all(np.isfinite(target)) else centers.mean(0)
    scale = float(config.scale) if config.scale else ref / LEVIR_REFERENCE_DEPTH
    return SceneGeometry(cams, [np.asarray(v.image, np.float32) for v in views], [v.depth for v in views],
                         up, float(conf), up_frame(up), origin, nadir_angle_deg(cams, up), scale, ref)


def run_sparse(geo: SceneGeometry, config: InitConfig, report: Report) -> SparseCloud:
    """SfM with the poses fixed; an empty cloud (with the reason) when it finds too few points."""
    t = time.time()
    try:
        sparse = triangulate_known_poses(geo.cameras, geo.images, origin=geo.origin, config=config.sfm)
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
                              config.depth_model, config.mvs)
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


def refine_cloud(geo: SceneGeometry, config: InitConfig, depths: list[np.ndarray], refine: str, report: Report
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Fuse the views' depths with the chosen refinement. Returns dense (points, colors), not downsampled."""
    if refine == "reproject":
        depths = reproject_max_depth(geo.cameras, depths)
    pts, cols, _ = backproject_views(geo.cameras, depths, geo.images)
    report.values["dense_points"] = len(pts)
    if refine != "no-ovlp":
        report.decide(STAGE, "overlap_removal", False, f"refinement '{refine}' chosen")
        return pts, cols
    ok, why = overlap_applicable(geo, config)
    if not report.decide(STAGE, "overlap_removal", ok, why):
        return pts, cols
    s = geo.scale
    local = to_frame(pts, geo.frame, geo.origin)
    t = time.time()
    dip = dip_cells(local, config.dip_cell * s, config.dip_alpha, config.dip_min_points)
    report.values["dip_s"] = time.time() - t
    report.decide(STAGE, "dip_test", dip.n_multimodal > 0,
                  f"{dip.n_multimodal} of {dip.n_tested} tested cells multimodal (p < {config.dip_alpha})"
                  + ("" if dip.n_multimodal else ": no overlap to remove"),
                  cells=dip.n_cells, tested=dip.n_tested, multimodal=dip.n_multimodal)
    if dip.n_multimodal == 0:
        return pts, cols
    drop = overlap_pairs_drop(local, dip.in_multimodal, config.dip_cell * s, config.eps_xy * s, config.eps_z * s)
    report.values["overlap_dropped"] = int(drop.sum())
    log.info("overlap removal: dropped %d of %d points", drop.sum(), len(pts))
    return pts[~drop], cols[~drop]


def initialise(scene: Any, out_dir: str | Path, config: InitConfig | None = None) -> InitResult:
    """Run the whole initialisation and write ``points.ply``, ``height_map.npz`` and ``init_report.json``."""
    cfg = config or InitConfig()
    out = Path(out_dir)
    report = Report()
    t0 = time.time()
    geo = scene_geometry(scene, cfg)
    report.values.update(up=geo.up, up_confidence=geo.up_confidence, nadir_deg=geo.nadir_deg, scale=geo.scale,
                         origin=geo.origin, ref_distance=geo.ref_distance, config=_config_dict(cfg),
                         inputs=init_inputs(scene, cfg), train=[c.name for c in geo.cameras])
    sparse = run_sparse(geo, cfg, report)
    density = len(sparse) / max(geo.n_pixels, 1)
    use_prior = density < cfg.dense_sfm_ratio
    report.decide(STAGE, "depth_prior", use_prior,
                  f"SfM gives {density:.4f} points per training pixel "
                  + (f"< {cfg.dense_sfm_ratio}: densify with a prior" if use_prior else f">= {cfg.dense_sfm_ratio}: already dense"))
    pts, cols = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    if use_prior:
        depths = prior_depths(geo, cfg, sparse.points, report)
        pts, cols = refine_cloud(geo, cfg, depths, cfg.refine, report)
    dense_pts = pts
    if len(pts):
        pts, cols = voxel_downsample(pts, cols, cfg.voxel * geo.scale, geo.origin)
    report.values["voxel_points"] = len(pts)
    pts = np.concatenate([pts, sparse.points])
    cols = np.concatenate([cols, sparse.colors])
    if len(pts) == 0:
        # Nothing triangulated nor matched: a plane through the look-at point keeps training possible.
        pts, cols = _plane_fallback(geo)
        dense_pts = pts
        report.decide(STAGE, "plane_fallback", True, "no SfM points and no prior depth: a plane at the cameras' "
                      "look-at point stands in for the scene")
    finite = np.isfinite(pts).all(1)
    pts, cols = pts[finite], cols[finite]
    report.values["points"] = len(pts)

    hm = None
    ok, why = overlap_applicable(geo, cfg)
    if report.decide(STAGE, "height_map", ok, why):
        src = np.concatenate([dense_pts, sparse.points]) if len(dense_pts) else pts
        hm = HeightMap.build(src, geo.frame, geo.origin, cfg.height_cell * geo.scale, cfg.height_percentile,
                             cfg.height_relax, cfg.height_margin * geo.scale)
    report.values["init_s"] = time.time() - t0 - float(report.values.get("model_load_s", 0.0))

    write_ply(out / "points.ply", pts, cols)
    hm_path = out / "height_map.npz"
    if hm is not None:
        hm.save(hm_path)
    elif hm_path.exists():
        hm_path.unlink()  # a stale map from an earlier run must not be picked up
    report.save(out / "init_report.json")
    return InitResult(pts, cols, hm, report)


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
    if inputs is not None and report.values.get("inputs") != inputs:
        log.info("%s was made from other training views; initialising again", out)
        return None
    if old.get("depth_prior") != config.depth_prior or old.get("depth_model") != config.depth_model:
        log.info("%s was made with another depth prior; initialising again", out)
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
    half = geo.ref_distance * 0.5
    g = np.linspace(-half, half, n)
    a, b = np.meshgrid(g, g)
    P = geo.origin + a.reshape(-1, 1) * F[0] + b.reshape(-1, 1) * F[1]
    return P, np.full((len(P), 3), 128, np.uint8)


def _config_dict(cfg: InitConfig) -> dict:
    d = asdict(cfg)
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in d.items()}
