"""Pseudo views by progressive depth-image-based rendering (paper: "Pseudo View Supervision
through Progressive DIBR").

For each pseudo camera sampled along the training cameras' acquisition trajectory
(:mod:`dibrgs_core.camera.trajectory`: on an orbit, along flight strips, or between
neighbouring cameras) or taken from a path the caller gives:

1. depth: z-buffer projection of the dense point cloud (:func:`zbuffer_depth`),
   then depth completion (:func:`complete_depth`): small gaps from their
   neighbours; large holes, for near-nadir scenes, from the rasterised height
   field of the cloud (:class:`~dibrgs_core.geometry.surface.HeightField`), else
   from the nearest valid pixel;
2. colour: every target pixel is back-projected with that depth and projected
   once into each training view (:func:`sample_sources`); a source fills only
   pixels that are still empty and that it sees (occlusion test against the
   source's own depth map of the same cloud), nearest source first
   (:func:`fill_progressive`);
3. what no source sees is padded and flagged, so the trainer can mask it;
4. warped pixels that two sources see but colour differently (wrong depth, most
   likely) are rejected from supervision (:func:`disagreement`); with the
   height field, each pixel takes whichever of the two depths the sources agree
   on better.

Sampled poses are kept only where the cloud covers the view, and a view whose
warped share is too small is dropped (:func:`build_pseudo_views`).

Conventions: OpenCV cameras from :mod:`dibrgs_core.camera.pinhole`, pixel centres at
+0.5, z-depth in world units along the camera axis, 0 marks "no depth".
Whole-image NumPy / torch on the CPU.
"""
from __future__ import annotations

import hashlib
import json
import logging
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import closing
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from scipy import ndimage

from ..camera.pinhole import Camera
from ..camera.frame import scene_depth
from ..camera.trajectory import Trajectory, classify, sample_poses
from ..common.fileio import atomic_path, write_json
from ..data.images import fill_no_data
from ..data.scene import View
from ..geometry.pointcloud import point_spacing
from .pseudo_depth import complete_depth, zbuffer_depth
from .pseudo_warp import PADDED, RTOL, Projector, disagreement, fill_progressive, merge_samples, source_order

log = logging.getLogger("dibrgs.pseudo_views")

_CACHE_VERSION = "pseudo-v6"  # v6: look jitter in proportion to the lens's span


@dataclass
class PseudoView:
    """A synthesised supervision view.

    Attributes:
        camera: the pseudo camera.
        image: float32 (H,W,3) in [0,1].
        valid: bool (H,W), pixels warped from a training view that sees them.
        padded: bool (H,W), pixels filled by padding (less reliable); never
            also ``valid``. Pixels neither valid nor padded are black holes.
        depth: float32 (H,W) completed z-depth used for warping (0 = none).
        rejected: bool (H,W), warped pixels left out of supervision because
            the sources that see them disagree on their colour; neither
            ``valid`` nor ``padded``.
    """

    camera: Camera
    image: np.ndarray
    valid: np.ndarray
    padded: np.ndarray
    depth: np.ndarray | None = None
    rejected: np.ndarray | None = None


@dataclass
class PseudoBuild:
    """What :func:`build_pseudo_views` made, and how.

    Attributes:
        views: the kept pseudo views.
        trajectory: the training cameras' trajectory (None with a user path).
        tried: sampled poses built or rejected before ``len(views)`` were kept.
        dropped_cloud: poses left out because the dense cloud covers too little of the view.
        dropped_warped: views dropped because too little of them is warped.
        thin: names of the user path's poses kept with less than ``min_warped`` of their pixels
            warped (mostly padding: the path leaves what the training photos saw); a path is
            taken pose by pose, so these are reported, not dropped.
        cpu_s: process CPU seconds the build took (0 when loaded from the cache).
        cached: loaded from the cache.
    """

    views: list[PseudoView]
    trajectory: Trajectory | None = None
    tried: int = 0
    dropped_cloud: int = 0
    dropped_warped: int = 0
    thin: list[str] = field(default_factory=list)
    cpu_s: float = 0.0
    cached: bool = False

    def mean_fractions(self) -> dict[str, float]:
        """Mean warped / padded / rejected share of the kept views' pixels (0 without views)."""
        def mean(key: str) -> float:
            xs = [getattr(v, key).mean() for v in self.views if getattr(v, key) is not None]
            return float(np.mean(xs)) if xs else 0.0

        return {"warped": mean("valid"), "padded": mean("padded"), "rejected": mean("rejected")}


# ---------------------------------------------------------------------------
# Depth
# ---------------------------------------------------------------------------


# ---------------------------------------------------------------------------
# Warping
# ---------------------------------------------------------------------------


# ---------------------------------------------------------------------------
# Building and caching
# ---------------------------------------------------------------------------
#: Defaults of :func:`build_pseudo_views`' pose filters (fractions of the view's pixels).
MIN_CLOUD_COVER = 0.5
MIN_WARPED = 0.2
#: At most this many sampled poses per requested view are tried.
CANDIDATES_PER_VIEW = 3


def _hash_inputs(train_views: Sequence, points: np.ndarray, options: dict, path: Sequence[Camera] | None) -> str:
    """Key of a pseudo-view set: the version, every training view (camera, name, image), the
    cloud, every option and the user path."""
    h = hashlib.sha256(_CACHE_VERSION.encode())
    h.update(np.ascontiguousarray(points, dtype=np.float64).tobytes())
    h.update(json.dumps(options, sort_keys=True).encode())

    def cam(c: Camera) -> None:
        h.update(np.ascontiguousarray(c.K).tobytes() + np.ascontiguousarray(c.w2c).tobytes())
        h.update(f"{c.width}x{c.height}:{c.name}".encode())

    h.update(f"views={len(train_views)}".encode())
    for v in train_views:
        cam(v.camera)
        img = np.ascontiguousarray(_source_image(v))
        h.update(f"{img.shape}".encode())
        h.update(img.tobytes())
    h.update(f"path={path is not None}:{len(path or [])}".encode())
    for c in path or []:
        cam(c)
    return h.hexdigest()


def _source_image(v: View) -> np.ndarray:
    """A training view's float32 (H, W, 3) RGB as a warp's source: NaN where it holds no data, which
    the warp treats as not visible (:meth:`~.pseudo_warp.Projector.sample`)."""
    image, valid = v.pixels()
    # Contiguous: every warp hands it to torch, which would copy a strided one each time.
    return np.ascontiguousarray(fill_no_data(np.asarray(image, np.float32)[..., :3], valid, np.nan))


def _save_view(p: Path, pv: PseudoView) -> None:
    """One view as an uncompressed ``.npz`` (floats barely compress, and compressing cost more
    than building the view); the image is float16, as :func:`_build_one` rounds it."""
    c = pv.camera
    arrays = {"K": c.K, "w2c": c.w2c, "size": np.array([c.width, c.height]), "name": np.array(c.name),
              "image": pv.image.astype(np.float16), "valid": pv.valid, "padded": pv.padded,
              "depth": np.zeros((0,), np.float32) if pv.depth is None else pv.depth,
              "rejected": np.zeros((0,), bool) if pv.rejected is None else pv.rejected}
    with atomic_path(p) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)


def _load_view(p: Path) -> PseudoView:
    with np.load(p, allow_pickle=False) as z:
        W, H = (int(v) for v in z["size"])
        cam = Camera(K=z["K"], w2c=z["w2c"], width=W, height=H, name=str(z["name"]))
        depth, rejected = z["depth"], z["rejected"]
        return PseudoView(cam, z["image"].astype(np.float32), z["valid"].astype(bool), z["padded"].astype(bool),
                          depth if depth.size else None, rejected.astype(bool) if rejected.size else None)


def _load_cache(cache_dir: Path, key: str) -> tuple[list[PseudoView], dict] | None:
    man = cache_dir / "manifest.json"
    if not man.is_file():
        return None
    try:
        m = json.loads(man.read_text())
        if m.get("hash") != key:
            return None
        return [_load_view(cache_dir / f) for f in m["files"]], m.get("stats", {})
    except (OSError, ValueError, KeyError, TypeError) as e:
        log.warning("pseudo-view cache in %s unreadable (%s); rebuilding", cache_dir, e)
        return None


def build_pseudo_views(train_views: Sequence, points: np.ndarray, n: int, seed: int, cache_dir: str | Path,
                       path: Sequence[Camera] | None = None, max_gap_px: float = 4.0,
                       surface: bool = False, consistency_tol: float = 0.0,
                       min_cloud_cover: float = MIN_CLOUD_COVER, min_warped: float = MIN_WARPED,
                       jitter: float = 0.1, look_jitter_deg: float = 2.0,
                       on_progress: Callable[[int, int], None] | None = None) -> PseudoBuild:
    """Build (or load from ``cache_dir``) the progressive-DIBR pseudo views.

    Args:
        train_views: :class:`~dibrgs_core.data.scene.View` objects (camera + image), the sources.
        points: (N,3) dense point cloud in world units.
        n: number of pseudo views wanted (ignored when ``path`` is given).
        seed: seed of the pose sampling.
        cache_dir: folder for ``view_NNN.npz`` files and ``manifest.json``; the manifest
            stores a hash of every input (the training cameras, names and images, the
            cloud, every option, the path, the code version), so changed inputs - another
            scene, another split - rebuild and identical ones load (resume) - and each kept
            view's warped, padded and rejected fractions (``views``). Files are
            written atomically and the manifest last.
        path: cameras to use instead of sampled poses; all are kept, none filtered (poses with
            less than ``min_warped`` warped are named in ``thin``).
        max_gap_px: warped pixels farther than this (pixels) from any pixel the cloud
            projects to have completed, not measured, depth; they are returned as
            ``padded`` rather than ``valid``.
        surface: complete large depth holes (target and source views) from the
            rasterised :class:`~dibrgs_core.geometry.surface.HeightField` of ``points``
            instead of the nearest valid pixel; for near-nadir scenes.
        consistency_tol: warped pixels that at least two sources see with a mean absolute
            RGB difference above this (image units in [0,1]) are ``rejected``; 0 keeps
            them all. With ``surface`` too, a pixel whose completed-cloud depth and
            height-field depth are both seen by two sources takes the one they agree on
            better (floating MVS points over a street hidden from one view otherwise win
            the z-buffer).
        min_cloud_cover: a sampled pose is skipped when less than this share of its pixels
            lies within ``max_gap_px`` of a pixel the cloud projects to.
        min_warped: a sampled view is dropped when less than this share of its pixels is
            warped (``valid``).
        jitter, look_jitter_deg: pose jitter (:func:`~dibrgs_core.camera.trajectory.sample_poses`).
        on_progress: called with (views kept, views wanted) before the first and after each
            kept view while views are built (not when they load from the cache).

    Sampled poses come from :func:`~dibrgs_core.camera.trajectory.classify` of the training
    cameras; up to :data:`CANDIDATES_PER_VIEW` x ``n`` are tried, in their seeded order,
    until ``n`` are kept.
    """
    from tqdm import tqdm

    cache_dir = Path(cache_dir)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    options = {"n": n, "seed": seed, "max_gap_px": max_gap_px, "surface": surface,
               "consistency_tol": consistency_tol, "min_cloud_cover": min_cloud_cover, "min_warped": min_warped,
               "jitter": jitter, "look_jitter_deg": look_jitter_deg, "candidates": CANDIDATES_PER_VIEW}
    key = _hash_inputs(train_views, pts, options, path)
    train_cams = [v.camera for v in train_views]
    traj = None if path is not None else classify(train_cams, scene_depth=scene_depth(pts, train_cams))
    cached = _load_cache(cache_dir, key)
    if cached is not None:
        views, stats = cached
        log.info("loaded %d pseudo views from %s", len(views), cache_dir)
        return PseudoBuild(views, traj, int(stats.get("tried", len(views))), int(stats.get("dropped_cloud", 0)),
                           int(stats.get("dropped_warped", 0)), list(stats.get("thin", [])), 0.0, True)
    t0 = time.process_time()
    if path is not None:
        cams, filtered = list(path), False
    elif n > 0 and train_cams:
        cams, filtered = sample_poses(traj, train_cams, CANDIDATES_PER_VIEW * n, seed, jitter, look_jitter_deg), True
    else:
        cams, filtered = [], False
    spacing = point_spacing(pts)
    hfield = None
    if surface and len(pts):
        from ..geometry.surface import HeightField

        hfield = HeightField.build(pts, train_cams)
    sources = []
    for v in train_views:
        fill = None if hfield is None else hfield.depth(v.camera)
        sources.append((v.camera, _source_image(v),
                        complete_depth(zbuffer_depth(pts, v.camera, spacing), fill=fill)))
    check = consistency_tol > 0 and len(sources) > 1
    (cache_dir / "manifest.json").unlink(missing_ok=True)  # a crash mid-rebuild must not look complete
    out, files, per_view, thin = [], [], [], []
    tried = dropped_cloud = dropped_warped = 0
    total = len(cams) if not filtered else n
    bar = tqdm(total=total, desc="pseudo views", unit="view", leave=False)
    if on_progress is not None:
        on_progress(0, total)
    # Views are independent: built ahead on the torch threads' count of Python threads (numpy,
    # scipy and torch release the GIL for most of a view), consumed in order as if one by one.
    common = (pts, spacing, hfield, sources, check, consistency_tol, max_gap_px, min_cloud_cover if filtered else 0.0)
    with closing(_in_order(_build_one, ((cam, *common) for cam in cams), torch.get_num_threads())) as results:
        while not (filtered and len(out) >= n):
            item = next(results, None)
            if item is None:
                break
            (cam, *_), pv = item
            tried += 1
            if pv is None:
                dropped_cloud += 1
                continue
            if pv.valid.mean() < min_warped:
                if filtered:
                    dropped_warped += 1
                    continue
                thin.append(cam.name or f"pose {tried - 1}")
            pv.camera.name = f"pseudo_{len(out):03d}" if filtered else cam.name
            fname = f"view_{len(out):03d}.npz"
            _save_view(cache_dir / fname, pv)
            files.append(fname)
            out.append(pv)
            bar.update(1)
            if on_progress is not None:
                on_progress(len(out), total)
            fractions = {"warped": float(pv.valid.mean()), "padded": float(pv.padded.mean()),
                         "rejected": 0.0 if pv.rejected is None else float(pv.rejected.mean())}
            per_view.append({"name": pv.camera.name, "file": fname, **fractions})
            # Per view at debug level: on the console these lines would bury the progress bar; the
            # manifest keeps them and the caller logs the means.
            log.debug("pseudo view %s: %.1f%% warped, %.1f%% padded, %.1f%% rejected", pv.camera.name,
                      *(100 * f for f in fractions.values()))
    bar.close()
    stats = {"tried": tried, "dropped_cloud": dropped_cloud, "dropped_warped": dropped_warped, "thin": thin}
    write_json(cache_dir / "manifest.json", {"hash": key, "files": files, "count": len(files), "stats": stats,
                                             "views": per_view})
    return PseudoBuild(out, traj, tried, dropped_cloud, dropped_warped, thin, time.process_time() - t0)


def _in_order(fn: Callable[..., Any], jobs: Iterable[tuple], workers: int) -> Iterator[tuple[tuple, Any]]:
    """``(job, fn(*job))`` for each of ``jobs`` in order, up to ``workers`` of them computed ahead
    on threads (one: each when asked for). Closing the generator cancels the jobs not started."""
    if workers <= 1:
        for job in jobs:
            yield job, fn(*job)
        return
    pool = ThreadPoolExecutor(max_workers=workers)
    todo = iter(jobs)
    pending = deque((job, pool.submit(fn, *job)) for job in islice(todo, workers))
    try:
        while pending:
            job, future = pending.popleft()
            result = future.result()
            for nxt in islice(todo, 1):
                pending.append((nxt, pool.submit(fn, *nxt)))
            yield job, result
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def _build_one(cam: Camera, pts: np.ndarray, spacing: float, hfield, sources: list[tuple], check: bool,
               consistency_tol: float, max_gap_px: float, min_cloud_cover: float) -> PseudoView | None:
    """One pseudo view (None when the cloud covers less than ``min_cloud_cover`` of it)."""
    shape = (cam.height, cam.width)
    raw = zbuffer_depth(pts, cam, spacing)
    # Depth invented far from any projected point (outside the cloud) is a guess: its warped
    # colour is demoted to padding.
    if (raw > 0).any():
        guessed = ndimage.distance_transform_edt(raw <= 0) > max_gap_px
    else:
        guessed = np.ones(shape, bool)
    if min_cloud_cover > 0 and 1.0 - guessed.mean() < min_cloud_cover:
        return None
    surf = None if hfield is None else hfield.depth(cam)
    depth = complete_depth(raw, fill=surf)
    proj = Projector(cam, sources)
    samples = proj.sample(depth, sources, RTOL)
    count = spread = None
    if check:
        count, spread = disagreement(samples, shape)
        if surf is not None:
            # Two depth hypotheses, the completed cloud and the height field: where both are
            # seen by two sources, keep the one whose colours agree more. Floating MVS points in
            # front of occluded streets lose to the ground.
            s_surf = proj.sample(surf, sources, RTOL)
            c2, s2 = disagreement(s_surf, shape)
            take = (count >= 2) & (c2 >= 2) & (s2 < spread) & (surf > 0)
            if take.any():
                depth = np.where(take, surf, depth).astype(np.float32)
                count, spread = np.where(take, c2, count), np.where(take, s2, spread)
                samples = merge_samples(samples, s_surf, take.ravel())
    image, valid, filled_by = fill_progressive(samples, source_order(cam, sources), shape)
    image = image.astype(np.float16).astype(np.float32)  # as cached (8-bit sources: far below their step)
    padded = filled_by == PADDED
    padded |= valid & guessed
    valid &= ~guessed
    rejected = None
    if check:
        rejected = (valid | padded) & (count >= 2) & (spread > consistency_tol)
        valid &= ~rejected
        padded &= ~rejected
    return PseudoView(cam, image, valid, padded, depth, rejected)
