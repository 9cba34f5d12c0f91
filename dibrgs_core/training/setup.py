"""Building a run's training method from the scene: the one place where the methods differ.

* ``dibrgs``: geometry initialisation (reused from ``WORK/init`` when it was made with the
  same options), anchors on the dense cloud (or SfM points, ablation), the height
  constraint, the IBR encoder, and progressive-DIBR pseudo views;
* ``3dgs``: SfM points of the training views (``WORK/init/sfm_points.npz``), topped up
  with random points in the viewed volume when SfM finds too few (3DGS's own fallback).

A resumed run rebuilds the model with the checkpoint's shapes in the same order, so
the random number streams match a run that was never stopped.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..camera.frame import estimate_up, look_at_target, up_frame
from ..camera.pinhole import Camera
from ..common.fileio import atomic_path
from ..common.report import Report
from ..common.digest import Digest
from ..common.errors import InputError
from ..data.scene import Scene, View, views_digest
from .config import TrainConfig
from .frames import Frame, frame_valid
from .methods import GS3DTraining, ScaffoldTraining, TrainingMethod
from .run_folder import PSEUDO_PATH_DIGEST

log = logging.getLogger("dibrgs.train")


@dataclass
class SetupContext:
    """What building a method needs: the run's configuration, folder and report, the scene and
    its training frames (the scene's images resized by ``resolution_scale``), the set-up random
    generator, the checkpoint to resume (or None)."""

    cfg: TrainConfig
    work: Path
    scene: Scene
    train_frames: list[Frame]
    report: Report
    rng: np.random.Generator
    ckpt: dict[str, Any] | None
    depth_model: str | None = None
    # Announces a long set-up stage: (what, done, total), counts None when unknown.
    stage: Callable[[str, int | None, int | None], None] = lambda what, done=None, total=None: None
    resolution_scale: float = 1.0


@dataclass
class Setup:
    """A built method and its pseudo-view frames (empty when pseudo views do not apply)."""

    method: TrainingMethod
    pseudo_frames: list[Frame]


def sfm_points(ctx: SetupContext) -> tuple[np.ndarray, np.ndarray]:
    """SfM points (N,3) and colours (N,3) uint8 of the training views, cached in ``WORK/init``
    under a digest of the training views (cameras and images) and the SfM options."""
    from dataclasses import asdict

    from ..geometry.config import SfmConfig
    from ..geometry.sfm import triangulate_known_poses

    views = ctx.scene.train_views()
    cache = ctx.work / "init" / "sfm_points.npz"
    sfm_options = asdict(SfmConfig())
    key = Digest("sfm_points/1").text(views_digest(views)).json(sfm_options).hex()
    if cache.exists():
        try:
            with np.load(cache) as d:
                if "key" in d.files and str(d["key"]) == key:
                    return d["points"], d["colors"]
            log.info("%s was made from other views or options; triangulating again", cache)
        except (OSError, ValueError, KeyError) as e:
            log.warning("%s unreadable (%s); triangulating again", cache, e)
    pixels = [v.pixels() for v in views]
    sc = triangulate_known_poses([v.camera for v in views], [p[0] for p in pixels], valid=[p[1] for p in pixels])
    with atomic_path(cache) as tmp:
        np.savez(tmp, points=sc.points, colors=sc.colors, key=np.array(key))
    return sc.points, sc.colors


def random_init(cams: list[Camera], n: int, rng: np.random.Generator,
                sparse_points: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random points (and grey colours in [0,1]) in the volume the cameras look at.

    A flat box, horizontally as wide as the mean image footprint there and vertically a
    quarter of that, around where the cameras' optical axes meet the ground
    (:func:`~dibrgs_core.geometry.sweep_range.scene_ground`: their convergence point when the
    axes determine one, else the SfM points' ground): on a mapping grid the axes are nearly
    parallel and their least-squares meeting point lands anywhere. Without either, that
    least-squares point.
    """
    from ..geometry.sweep_range import scene_ground

    up, _ = estimate_up(cams)
    n_up = np.asarray(up, np.float64) / np.linalg.norm(up)
    ground = scene_ground(cams, n_up, sparse_points)
    hits = []
    if ground is not None:
        for c in cams:
            down = -float(c.view_dir @ n_up)
            if down > 0.1:  # the axis reaches the ground in front of the camera
                hits.append(c.center + c.view_dir * (float(n_up @ c.center) - ground[0]) / down)
    target = np.mean(hits, axis=0) if hits else look_at_target(cams)
    R = up_frame(up)
    half = float(np.mean([np.linalg.norm(c.center - target) * c.width / (2 * c.K[0, 0]) for c in cams]))
    local = rng.uniform(-1, 1, (n, 3)) * np.array([half, half, half / 4])
    return target + local @ R, np.full((n, 3), 0.5)


def build_3dgs(ctx: SetupContext) -> Setup:
    from ..models.gs3d import Gaussians3D

    cfg, rep = ctx.cfg, ctx.report
    centers = np.stack([f.cam.cam.center for f in ctx.train_frames])
    # 3DGS's cameras_extent: 1.1 x the largest camera distance from their mean.
    extent = max(1.1 * float(np.max(np.linalg.norm(centers - centers.mean(0), axis=1))), 1e-6)
    if ctx.ckpt is not None:
        model = Gaussians3D.from_state(ctx.ckpt["method"]["model"])
    else:
        pts, cols = sfm_points(ctx)
        if len(pts) >= cfg.gs3d.min_sfm_points:
            rep.decide("train", "sfm_init", True, f"3DGS baseline starts from {len(pts)} SfM points")
            cols = np.asarray(cols, np.float64) / 255.0
        else:
            rp, rc = random_init([f.cam.cam for f in ctx.train_frames], cfg.gs3d.random_points, ctx.rng,
                                 np.asarray(pts).reshape(-1, 3))
            rep.decide("train", "sfm_init", False,
                       f"SfM found only {len(pts)} points (< {cfg.gs3d.min_sfm_points}); "
                       f"3DGS starts from {len(rp)} random points in the viewed volume as well")
            pts = np.concatenate([np.asarray(pts).reshape(-1, 3), rp])
            cols = np.concatenate([np.asarray(cols, np.float64).reshape(-1, 3) / 255.0, rc])
        model = Gaussians3D(pts, cols, cfg.gs3d.sh_degree)
    rep.values["extent"] = extent
    return Setup(GS3DTraining(model, cfg, extent, colour_transforms(ctx)), [])


def colour_transforms(ctx: SetupContext) -> Any:
    """The training views' colour transforms when they apply (:mod:`.appearance`)."""
    from .appearance import build_colour_transforms

    return build_colour_transforms(ctx.cfg.colour, [f.cam.cam for f in ctx.train_frames], ctx.report)


def init_geometry(ctx: SetupContext) -> Any:
    """The geometry initialisation of ``WORK/init``, reused only when it was made from the same
    training views (cameras, images; depth maps for the ``gt`` prior) with the same prior."""
    from ..geometry.config import InitConfig
    from ..geometry.pipeline import init_inputs, initialise, load_result

    icfg = InitConfig()
    if ctx.cfg.depth_prior != "auto":
        icfg.depth_prior = ctx.cfg.depth_prior
    if ctx.depth_model:
        icfg.depth_model = ctx.depth_model
    out = ctx.work / "init"
    inputs = init_inputs(ctx.scene, icfg)
    cached = load_result(out, icfg, inputs)
    if cached is not None:
        return cached
    ctx.stage("geometry initialisation (SfM, depth, dense points)", None, None)
    return initialise(ctx.scene, out, icfg)


def _says_near_nadir(report: Report) -> bool | None:
    """What the geometry report says about near-nadir views (None when it says nothing)."""
    for key in ("near_nadir", "height_map"):
        v = report.applied(key)
        if v is not None:
            return bool(v)
    val = report.values.get("near_nadir")
    return None if val is None else bool(val)


def build_dibrgs(ctx: SetupContext) -> Setup:
    from ..models.scaffold import NeuralGaussians, build_model

    cfg, rep = ctx.cfg, ctx.report
    res = init_geometry(ctx)
    scale = res.report.values.get("scale")
    if not scale:
        from ..geometry.config import InitConfig
        from ..geometry.scene_geometry import scene_geometry

        scale = scene_geometry(ctx.scene, InitConfig()).scale
    if cfg.dense_init:
        # float32-rounded, so a fresh cloud and one re-read from points.ply are the same
        # numbers (the pseudo-view cache is keyed on them).
        points = np.asarray(res.points, np.float32).astype(np.float64)
        rep.decide("train", "dense_init", True, f"anchors from the dense initial cloud ({len(points)} points)")
    else:
        points, _ = sfm_points(ctx)
        points = np.asarray(points, np.float32).astype(np.float64).reshape(-1, 3)
        if not len(points):
            raise InputError(None, "--no-dense-init: SfM triangulated no points in the training views, so the "
                                   "ablation has no anchors to start from; train without --no-dense-init")
        rep.decide("train", "dense_init", False, f"ablation --no-dense-init: anchors from {len(points)} SfM points")
    hm = res.height_map
    if cfg.height == "off":
        rep.decide("train", "height_constraint", False, "switched off (--no-height)")
        hm = None
    elif hm is None:
        rep.decide("train", "height_constraint", False,
                   "the geometry stage built no height map (scene not near-nadir or too few points)")
    elif cfg.height == "auto" and _says_near_nadir(res.report) is False:
        rep.decide("train", "height_constraint", False, "geometry report: the views are not near-nadir")
        hm = None
    else:
        rep.decide("train", "height_constraint", True, "height map vetoes coarse-level growth above its relaxed bound")
    # The IBR encoder's projection is initialised before the model's decoders (random streams).
    ibr = None
    if ctx.ckpt is None or ctx.ckpt["method"]["ibr"] is not None:
        ibr = build_ibr(ctx)
    if ctx.ckpt is not None:
        model = NeuralGaussians.from_state(ctx.ckpt["method"]["model"], cfg.model)
    else:
        centers = np.stack([f.cam.cam.center for f in ctx.train_frames])
        model, why = build_model(points, centers, cfg.model, use_ibr=ibr is not None, scale=float(scale))
        rep.values["anchor_voxel"] = why
    method = ScaffoldTraining(model, cfg, ibr, hm, colour_transforms(ctx))
    return Setup(method, pseudo_frames(ctx, points))


def build_ibr(ctx: SetupContext) -> Any:
    from ..models.ibr.features import build_ibr as build, resolve_encoder

    cfg = ctx.cfg
    name, reason = resolve_encoder(cfg.ibr, (cfg.dino_resnet, cfg.dino_vit))
    ctx.report.decide("train", "ibr_features", name != "none", f"encoder {name}: {reason}", encoder=name)
    if name == "none":
        return None
    imgs = [f.image.permute(2, 0, 1) for f in ctx.train_frames]
    cams = [f.cam.cam for f in ctx.train_frames]
    return build(name, imgs, cams, c_r=cfg.model.ibr_channels, dino_resnet=cfg.dino_resnet, dino_vit=cfg.dino_vit,
                 valid=[frame_valid(f) for f in ctx.train_frames])


def pseudo_frames(ctx: SetupContext, points: np.ndarray) -> list[Frame]:
    """Progressive-DIBR pseudo views of ``points`` as weighted frames (warped pixels weight 1,
    padded ones ``padded_weight``), or none when pseudo views do not apply.

    Records the training cameras' trajectory (the class and why), how many sampled views were
    kept and dropped, and their mean warped / padded / rejected shares in the report."""
    from ..geometry.surface import decide
    from ..models.base import CameraTensors
    from .pseudo_views import MIN_WARPED, build_pseudo_views

    cfg, rep = ctx.cfg, ctx.report
    n_train = len(ctx.train_frames)
    if cfg.pseudo.mode == "off":
        rep.decide("train", "pseudo_views", False, "switched off (--no-pseudo)")
        return []
    dense = cfg.pseudo.dense_reason(n_train)
    if dense is not None:
        rep.decide("train", "pseudo_views", False, dense)
        return []
    path = None
    if cfg.pseudo_path:
        from ..data.load import cameras_digest, read_any_cameras

        # A path's cameras are in the scene's pixels (the add-on copies a scene camera's
        # intrinsics): resized with the images, else the pseudo views would be rendered and
        # supervised at another resolution than the training views (3.5x the pixels at the cpu
        # preset's budget on a 953 px photo). Their poses are in the world frame of the scene's
        # files, where the add-on draws them: moved into the scene's own frame (Scene.origin).
        origin = ctx.scene.origin if ctx.scene is not None else np.zeros(3)
        read = read_any_cameras(cfg.pseudo_path)
        rep.values[PSEUDO_PATH_DIGEST] = cameras_digest(read)
        given = [c.translated(-origin) for c in read]
        path = [c.scaled(ctx.resolution_scale) if ctx.resolution_scale != 1.0 else c for c in given]
    cams = [f.cam.cam for f in ctx.train_frames]
    train_views = [View(c, f.image.numpy(), valid=frame_valid(f)) for c, f in zip(cams, ctx.train_frames)]
    surface, why = decide(cfg.pseudo.surface, cams)
    rep.decide("train", "pseudo_depth_height_field", surface, why)
    built = build_pseudo_views(train_views, np.asarray(points), cfg.pseudo.n_views, cfg.seed, ctx.work / "pseudo",
                               path=path, surface=surface, consistency_tol=cfg.pseudo.consistency_tol,
                               on_progress=lambda done, total: ctx.stage("building pseudo views", done, total))
    pvs, traj = built.views, built.trajectory
    if traj is not None:
        rep.decide("train", "pseudo_trajectory", True, f"{traj.kind}: {traj.reason}", kind=traj.kind,
                   spacing=traj.spacing, lines=traj.lines)
        where = f" along the {traj.kind} trajectory"
    else:
        rep.decide("train", "pseudo_trajectory", False, f"poses from the user path {cfg.pseudo_path}")
        where = f" on the path {cfg.pseudo_path}"
    fr = built.mean_fractions()
    rep.values["pseudo_views"] = {"kept": len(pvs), "wanted": len(path) if path is not None else cfg.pseudo.n_views,
                                  "tried": built.tried, "dropped_no_cloud": built.dropped_cloud,
                                  "dropped_few_warped": built.dropped_warped, "mean_warped": fr["warped"],
                                  "mean_padded": fr["padded"], "mean_rejected": fr["rejected"],
                                  "build_cpu_s": built.cpu_s, "cached": built.cached, "thin": built.thin}
    log.info("pseudo views: %d kept of %d tried (%d without enough cloud, %d with too few warped pixels); "
             "mean %.1f%% warped, %.1f%% padded, %.1f%% rejected; %.1f s CPU%s", len(pvs), built.tried,
             built.dropped_cloud, built.dropped_warped, 100 * fr["warped"], 100 * fr["padded"], 100 * fr["rejected"],
             built.cpu_s, " (cached)" if built.cached else "")
    if built.thin:
        # Measured on brighton_north: a third of a path moved off the photos' ground cost 0.14 dB
        # over the seen pixels and gained 0.3 dB over the unseen ones; the user may mean it, so
        # the poses stay and are named.
        log.warning("%d of the path's %d poses are mostly padding (under %.0f%% warped: they look where no "
                    "training photo saw): %s", len(built.thin), len(path or []), 100 * MIN_WARPED,
                    ", ".join(built.thin[:10]) + (" ..." if len(built.thin) > 10 else ""))
    if cfg.pseudo.consistency_tol > 0:
        rep.values["pseudo_rejected_fraction"] = fr["rejected"]
    frames, empty = [], 0
    for pv in pvs:
        weight = np.asarray(pv.valid, np.float32)
        if pv.padded is not None:
            weight = np.maximum(weight, cfg.pseudo.padded_weight * np.asarray(pv.padded, np.float32))
        if not (weight > 0).any():
            empty += 1
            continue
        frames.append(Frame(CameraTensors.of(pv.camera), torch.from_numpy(
            np.ascontiguousarray(np.clip(pv.image[..., :3], 0, 1), dtype=np.float32)), torch.from_numpy(weight)))
    why_dropped = [f"{n} {what}" for n, what in ((built.dropped_cloud, "where the cloud covered too little"),
                                                 (built.dropped_warped, "with too little warped")) if n]
    rep.decide("train", "pseudo_views", bool(frames),
               f"{len(frames)} progressive-DIBR pseudo views{where}"
               + (f" (sampled poses dropped: {', '.join(why_dropped)})" if why_dropped else "")
               + (f" ({empty} without any filled pixel left out)" if empty else "")
               + (f" ({len(built.thin)} of the path's poses mostly padding)" if built.thin else ""))
    return frames


#: The methods ``TrainConfig.method`` can name, and how each is built.
METHODS: dict[str, Callable[[SetupContext], Setup]] = {"dibrgs": build_dibrgs, "3dgs": build_3dgs}
