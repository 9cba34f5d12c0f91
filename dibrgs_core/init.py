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
from typing import Any, Literal, Sequence

import numpy as np

from .cameras import Camera, estimate_up, nadir_angle_deg, up_frame
from .depth_prior import MAPS, Alignment, align_view, compute_prior, map_disparity
from .errors import InputError
from .fusion import (_flat_keys, backproject_views, dip_cells, overlap_pairs_drop, reproject_max_depth, to_frame,
                     voxel_downsample_values, voxel_keys, write_ply)
from .height_map import HeightMap, completion_field
from .mvs import MvsConfig, converging_target
from .report import Report
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
        complete: fill the training pixels the prior left without depth from a
            height field of what it measured (:func:`complete_depths`):
            ``auto`` (near-nadir scenes), ``on`` or ``off``.
        completion_confidence: point confidence of completed depth (measured
            depth has 0.5 or more, see :class:`InitResult`).
        completion_cell_px: cell of the completion surface, in training-view
            pixels at the reference distance.
        completion_voxel: completed points are voxel-downsampled this many
            times coarser than measured ones (fewer anchors where the geometry
            is a guess).
    """

    depth_prior: str = "auto"
    depth_model: str | None = None
    depth_map: str = "inv"
    refine: str = "no-ovlp"
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
    max_nadir_deg: float = 60.0
    min_up_confidence: float = 0.5
    min_sfm_points: int = 20
    dense_sfm_ratio: float = 0.05
    complete: Literal["auto", "on", "off"] = "auto"
    completion_confidence: float = 0.25
    completion_cell_px: float = 4.0
    completion_voxel: float = 2.0
    sfm: SfmConfig = field(default_factory=SfmConfig)
    mvs: MvsConfig = field(default_factory=MvsConfig)


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
    (:func:`_overlap_distance`), until :func:`sfm_reference` replaces it with
    the depth of the SfM points. ``ref_source`` says which.
    """
    views = list(scene.train_views())
    if not views:
        raise InputError(getattr(scene, "root", None), "the scene has no training views")
    cams = [v.camera for v in views]
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
            ref, source = _overlap_distance(cams), "camera-spacing"
        # A point ``ref`` in front of the cameras' centroid: the ground below them, roughly.
        origin = centers.mean(0) + ref * np.mean([c.view_dir for c in cams], axis=0)
    scale = float(config.scale) if config.scale else ref / LEVIR_REFERENCE_DEPTH
    return SceneGeometry(cams, [np.asarray(v.image, np.float32) for v in views], [v.depth for v in views],
                         up, float(conf), up_frame(up), origin, nadir_angle_deg(cams, up), scale, ref, source)


def _overlap_distance(cams: Sequence[Camera]) -> float:
    """Distance to the scene if neighbouring photos overlapped by half (last resort, no SfM, no depth ranges):
    the median nearest-neighbour camera spacing is then half the footprint, ``d * mean(W, H) / f``."""
    C = np.stack([c.center for c in cams])
    if len(C) < 2:
        return 1.0
    D = np.linalg.norm(C[:, None] - C[None], axis=2) + np.diag(np.full(len(C), np.inf))
    spacing = float(np.median(D.min(1)))
    c0 = cams[0]
    size = 0.5 * (c0.width + c0.height)
    f = 0.5 * (c0.fx + c0.fy)
    d = 2.0 * spacing * f / max(size, 1.0)
    return d if np.isfinite(d) and d > 0 else 1.0


def sfm_reference(geo: SceneGeometry, sparse: SparseCloud, config: InitConfig, report: Report) -> None:
    """Replace a provisional reference distance (see :func:`scene_geometry`) by the median z-depth of the
    SfM points in the training views, and the origin by their median; the scale follows (unless
    ``config.scale`` is set)."""
    if geo.ref_source == "look-at" or len(sparse) < config.min_sfm_points:
        report.decide(STAGE, "scene_scale", True, f"reference distance {geo.ref_distance:.4g} from the "
                      f"{'point the cameras converge on' if geo.ref_source == 'look-at' else geo.ref_source}",
                      source=geo.ref_source, ref_distance=geo.ref_distance, scale=geo.scale)
        return
    depths = []
    for c in geo.cameras:
        uv, z = c.project(sparse.points)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
        depths.append(z[ok])
    z = np.concatenate(depths)
    if len(z) < config.min_sfm_points:
        report.decide(STAGE, "scene_scale", True, f"reference distance {geo.ref_distance:.4g} from the "
                      f"{geo.ref_source}: only {len(z)} SfM points in the views", source=geo.ref_source,
                      ref_distance=geo.ref_distance, scale=geo.scale)
        return
    old, old_source = geo.ref_distance, geo.ref_source
    geo.ref_distance = float(np.median(z))
    geo.origin = np.median(sparse.points, axis=0)
    geo.ref_source = "sfm"
    if not config.scale:
        geo.scale = geo.ref_distance / LEVIR_REFERENCE_DEPTH
    report.decide(STAGE, "scene_scale", True, f"the cameras' axes do not converge (parallel views): reference "
                  f"distance {geo.ref_distance:.4g} = median SfM point depth (provisional {old:.4g} from the "
                  f"{old_source})", source="sfm", ref_distance=geo.ref_distance, scale=geo.scale)


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


def near_nadir(up_confidence: float, nadir_deg: float, config: InitConfig) -> tuple[bool, str]:
    """Whether cameras with this up-axis agreement (:func:`cameras.estimate_up`) and mean angle from
    straight down (degrees) are near-nadir with a clear up axis, and why."""
    if up_confidence < config.min_up_confidence:
        return False, f"the up axis is ambiguous (camera agreement {up_confidence:.2f} < {config.min_up_confidence})"
    if nadir_deg > config.max_nadir_deg:
        return False, f"cameras are not near-nadir (mean {nadir_deg:.1f} deg from straight down > {config.max_nadir_deg})"
    return True, f"near-nadir cameras ({nadir_deg:.1f} deg from straight down, up agreement {up_confidence:.2f})"


def overlap_applicable(geo: SceneGeometry, config: InitConfig) -> tuple[bool, str]:
    """Overlap removal and the height map need near-nadir cameras and a clear up axis."""
    return near_nadir(geo.up_confidence, geo.nadir_deg, config)


def refine_cloud(geo: SceneGeometry, config: InitConfig, depths: list[np.ndarray], refine: str, report: Report,
                 confidence: list[np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fuse the views' depths with the chosen refinement.

    Returns the dense (points, colors, confidence), not downsampled; the
    confidence of a point is its pixel's in ``confidence`` (HxW maps, one per
    view; 1 everywhere when None).
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
    ``off``, or with too few measured points.
    """
    holes = sum(int((~(np.isfinite(d) & (np.asarray(d) > 0))).sum()) for d in depths)
    if config.complete == "off":
        report.decide(STAGE, "completion", False, "switched off")
        return depths, confidence
    ok, why = near_nadir(geo.up_confidence, geo.nadir_deg, config)
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
    for cam, d, c in zip(geo.cameras, depths, confidence):
        d = np.asarray(d, np.float64)
        hole = ~(np.isfinite(d) & (d > 0))
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
    """Depth (H,W) float64 of ``field`` seen by ``cam`` (0 = no surface), ray-cast at most ``max_size``
    pixels on the long side and upsampled: the surface is coarser than that, and casting every pixel of a
    large photo took a minute."""
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


def voxel_confident(points: np.ndarray, colors: np.ndarray, confidence: np.ndarray, voxel: float,
                    origin: np.ndarray, split: float = 0.5, completed_factor: float = 1.0
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxel-downsample measured points (confidence >= ``split``) and completed ones separately (mean
    position, colour and confidence per voxel; completed ones in voxels ``completed_factor`` times larger)
    and keep a completed voxel only where no measured point lies: completion fills holes, it never blends
    into what was measured."""
    if not voxel or voxel <= 0:
        return points, colors, confidence
    meas = confidence >= split
    Pm, Cm, Km = voxel_downsample_values(points[meas], colors[meas], confidence[meas], voxel, origin)
    big = voxel * max(completed_factor, 1.0)
    Pc, Cc, Kc = voxel_downsample_values(points[~meas], colors[~meas], confidence[~meas], big, origin)
    keep = ~_rows_in(voxel_keys(Pc, big, origin), voxel_keys(points[meas], big, origin))
    return np.concatenate([Pm, Pc[keep]]), np.concatenate([Cm, Cc[keep]]), np.concatenate([Km, Kc[keep]])


def _rows_in(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """For each row of integer array ``a`` (N,3), whether it occurs in ``b`` (M,3)."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(len(a), bool)
    flat = _flat_keys(np.concatenate([a, b]))
    return np.isin(flat[:len(a)], flat[len(a):])


def initialise(scene: Any, out_dir: str | Path, config: InitConfig | None = None) -> InitResult:
    """Run the whole initialisation and write ``points.ply``, ``height_map.npz`` and ``init_report.json``."""
    cfg = config or InitConfig()
    out = Path(out_dir)
    report = Report()
    t0 = time.time()
    geo = scene_geometry(scene, cfg)
    report.values.update(up=geo.up, up_confidence=geo.up_confidence, nadir_deg=geo.nadir_deg, config=_config_dict(cfg))
    sparse = run_sparse(geo, cfg, report)
    sfm_reference(geo, sparse, cfg, report)
    report.values.update(scale=geo.scale, origin=geo.origin, ref_distance=geo.ref_distance, ref_source=geo.ref_source)
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
                              cfg.depth_model, cfg.mvs)
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
