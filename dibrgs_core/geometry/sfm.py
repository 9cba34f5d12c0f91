"""Sparse structure from motion with known poses (pycolmap, CPU).

SIFT features of the training views, matching with geometric verification
(every pair, or each photo with its nearest ``SfmConfig.max_neighbours`` by
camera position), then triangulation with the given cameras held fixed: no pose
or intrinsics re-estimation. Coordinates are handed to COLMAP relative to a
local origin (georeferenced scenes have coordinates around 1e5, where float
precision inside COLMAP's solvers would suffer) and in units of the cameras'
spread around it (COLMAP's solvers have absolute tolerances: the same views in
millimetres or kilometres triangulated differently), and moved back afterwards.
"""
from __future__ import annotations

import contextlib
import logging
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from ..camera.pinhole import Camera
from ..common.colmap_lib import import_pycolmap
from ..data.images import to_uint8
from .config import SfmConfig

log = logging.getLogger("dibrgs.sfm")


@contextlib.contextmanager
def colmap_logging() -> Iterator[None]:
    """COLMAP's own INFO lines (some sixty a reconstruction, written to stderr by its logger) only
    when this package logs at DEBUG (``dibrgs -v``): otherwise they drown the stages' decisions.
    Its warnings and errors always show; the previous level is restored afterwards."""
    pycolmap = import_pycolmap()

    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = pycolmap.logging.INFO if log.isEnabledFor(logging.DEBUG) else pycolmap.logging.WARNING
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


@dataclass
class SparseCloud:
    """Triangulated points in world coordinates.

    Attributes:
        points: (N,3) float64 world positions.
        colors: (N,3) uint8 RGB.
        track_lengths: (N,) number of images observing each point.
        errors: (N,) mean reprojection error in pixels.
    """

    points: np.ndarray
    colors: np.ndarray
    track_lengths: np.ndarray
    errors: np.ndarray

    @classmethod
    def empty(cls) -> "SparseCloud":
        return cls(np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, np.int64), np.zeros(0))

    def __len__(self) -> int:
        return len(self.points)


def neighbour_pairs(cams: Sequence[Camera], k: int) -> list[tuple[int, int]] | None:
    """Index pairs (i < j) to match: each camera with its ``k`` nearest camera centres (a pair
    either side chose, once); None (every pair) when no camera has more than ``k`` others or
    ``k`` is 0."""
    n = len(cams)
    if k <= 0 or n - 1 <= k:
        return None
    from scipy.spatial import cKDTree

    centres = np.array([c.center for c in cams], np.float64)
    _, nearest = cKDTree(centres).query(centres, k=k + 1)
    pairs = {(min(i, int(j)), max(i, int(j))) for i in range(n) for j in nearest[i] if int(j) != i}
    return sorted(pairs)


#: Pixels by which features keep off the pixels of a photo without data.
MASK_MARGIN_PX = 4


def _number_in_order(pycolmap, db_path: Path) -> None:
    """Give the database's images and frames the ids of their names' order. COLMAP numbers them
    as their features are written, so photos extracted on several threads are numbered in the
    order they finish, and matching and triangulation follow the ids: the same points would come
    out in another order and rounding from one run or machine to the next."""
    db = pycolmap.Database.open(db_path)
    try:
        images = sorted(db.read_all_images(), key=lambda im: im.name)
        if [im.image_id for im in images] == sorted(im.image_id for im in images):
            return
        frames = {f.frame_id: f for f in db.read_all_frames()}
        features = {im.image_id: (db.read_keypoints(im.image_id), db.read_descriptors(im.image_id)) for im in images}
        for clear in (db.clear_keypoints, db.clear_descriptors, db.clear_images, db.clear_frames):
            clear()
        for k, im in enumerate(images, start=1):
            keypoints, descriptors = features[im.image_id]
            frame = frames[im.frame_id]
            frame.frame_id = k
            frame.clear_data_ids()
            frame.add_data_id(pycolmap.data_t(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, im.camera_id), k))
            db.write_frame(frame, use_frame_id=True)
            im.image_id, im.frame_id = k, k
            db.write_image(im, use_image_id=True)
            db.write_keypoints(k, keypoints)
            db.write_descriptors(k, descriptors)
    finally:
        db.close()


@colmap_logging()
def triangulate_known_poses(cameras: Sequence[Camera], images: Sequence[np.ndarray], origin: np.ndarray | None = None,
                            config: SfmConfig | None = None, work_dir: Path | None = None,
                            valid: Sequence[np.ndarray | None] | None = None) -> SparseCloud:
    """Sparse points from images with known cameras.

    Args:
        cameras: one :class:`Camera` per image (world units, OpenCV axes).
        images: HxWx3 float images in [0, 1].
        origin: local origin subtracted from world coordinates inside COLMAP
            (default: mean camera centre).
        config: :class:`SfmConfig`.
        work_dir: where COLMAP's database and images go (a temporary folder
            when None; removed afterwards).
        valid: per image, bool HxW pixels that hold data or None (all do): features are
            extracted only there (COLMAP's mask images).

    Returns a :class:`SparseCloud` (possibly empty; never raises for "too few
    matches").
    """
    pycolmap = import_pycolmap()
    import torch
    from PIL import Image

    cfg = config or SfmConfig()
    cams = list(cameras)
    if len(cams) != len(images):
        raise ValueError("one image per camera expected")
    if len(cams) < 2:
        return SparseCloud.empty()
    origin = np.mean([c.center for c in cams], axis=0) if origin is None else np.asarray(origin, np.float64)
    spread = float(np.median([np.linalg.norm(c.center - origin) for c in cams]))
    unit = spread if np.isfinite(spread) and spread > 0 else 1.0  # world units per COLMAP unit
    own_tmp = work_dir is None
    root = Path(tempfile.mkdtemp(prefix="dibrgs_sfm_")) if own_tmp else Path(work_dir)
    try:
        if root.exists() and not own_tmp:
            shutil.rmtree(root)
        img_dir = root / "images"
        img_dir.mkdir(parents=True)
        db_path = root / "database.db"
        names = [f"{i:04d}.png" for i in range(len(cams))]
        masked = valid is not None and any(m is not None for m in valid)
        for i, (name, img) in enumerate(zip(names, images)):
            Image.fromarray(to_uint8(img)).save(img_dir / name)
            if masked:
                from scipy.ndimage import binary_erosion

                # no features on no data, nor at its edge (a corner of a fill is no point of the scene)
                m = valid[i]
                keep = np.ones(img.shape[:2], bool) if m is None else binary_erosion(m, iterations=MASK_MARGIN_PX)
                (root / "masks").mkdir(exist_ok=True)
                Image.fromarray(keep.astype(np.uint8) * 255).save(root / "masks" / f"{name}.png")
        # One PINHOLE camera per image: created with the first camera's intrinsics, then given
        # each its own. SIFT of one image is the same on any thread: the photos are shared out
        # over torch's thread count (the matching and triangulation stay on one, see SfmConfig).
        eo = pycolmap.FeatureExtractionOptions()
        eo.num_threads = max(1, min(len(cams), torch.get_num_threads()))
        eo.sift.max_num_features = cfg.max_num_features
        c0 = cams[0]
        ro = pycolmap.ImageReaderOptions(camera_model="PINHOLE",
                                         camera_params=f"{c0.fx!r},{c0.fy!r},{c0.cx!r},{c0.cy!r}")
        if masked:
            ro.mask_path = str(root / "masks")
        pycolmap.extract_features(db_path, img_dir, image_names=names, camera_mode=pycolmap.CameraMode.PER_IMAGE,
                                  reader_options=ro, extraction_options=eo, device=pycolmap.Device.cpu)
        _number_in_order(pycolmap, db_path)
        by_name = dict(zip(names, cams))
        db = pycolmap.Database.open(db_path)
        try:
            for im in db.read_all_images():
                cam, c = db.read_camera(im.camera_id), by_name[im.name]
                cam.params = [c.fx, c.fy, c.cx, c.cy]
                db.update_camera(cam)
        finally:
            db.close()
        mo = pycolmap.FeatureMatchingOptions()
        mo.num_threads = 1
        vo = pycolmap.TwoViewGeometryOptions()
        vo.ransac.random_seed = cfg.seed
        pairs = neighbour_pairs(cams, cfg.max_neighbours)
        if pairs is None:
            pycolmap.match_exhaustive(db_path, matching_options=mo, verification_options=vo, device=pycolmap.Device.cpu)
        else:
            log.info("SfM: each of %d photos matched with its %d nearest (%d pairs of %d)", len(cams),
                     cfg.max_neighbours, len(pairs), len(cams) * (len(cams) - 1) // 2)
            (root / "pairs.txt").write_text("".join(f"{names[i]} {names[j]}\n" for i, j in pairs))
            po = pycolmap.ImportedPairingOptions()
            po.match_list_path = root / "pairs.txt"
            pycolmap.match_image_pairs(db_path, matching_options=mo, pairing_options=po, verification_options=vo,
                                       device=pycolmap.Device.cpu)

        db = pycolmap.Database.open(db_path)
        try:
            rec = pycolmap.Reconstruction()
            for c in db.read_all_cameras():
                rec.add_camera(c)
            for r in db.read_all_rigs():
                rec.add_rig(r)
            for f in db.read_all_frames():
                rec.add_frame(f)
            db_images = db.read_all_images()
            n_pairs = db.num_verified_image_pairs()
        finally:
            db.close()
        for im in db_images:
            rec.add_image(im)
        for im in db_images:
            cam = by_name[im.name]
            # Local frame: X_local = (X - origin) / unit, so t_local = (t + R @ origin) / unit.
            w2c = cam.w2c[:3].copy()
            w2c[:, 3] = (cam.t + cam.R @ origin) / unit
            rec.frame(im.frame_id).rig_from_world = pycolmap.Rigid3d(w2c)
            rec.register_frame(im.frame_id)
        if n_pairs == 0:
            log.info("SfM: no verified image pairs")
            return SparseCloud.empty()
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = 1
        opts.random_seed = cfg.seed
        opts.triangulation.ignore_two_view_tracks = not cfg.keep_two_view_tracks
        opts.triangulation.min_angle = cfg.min_angle_deg
        opts.triangulation.complete_max_reproj_error = cfg.max_reproj_error
        opts.triangulation.merge_max_reproj_error = cfg.max_reproj_error
        # The final filter has its own angle (COLMAP's 1.5 deg): one setting, not two.
        opts.mapper.filter_min_tri_angle = cfg.min_angle_deg
        # COLMAP skips images whose focal length is outside [0.1, 10] x their long side as badly
        # calibrated; ours are given. A telephoto or satellite lens (about 100) lost every point.
        # Only the pipeline's own setting counts: it overwrites the triangulator's and mapper's.
        ratios = [max(c.fx, c.fy) / max(c.width, c.height) for c in cams]
        opts.max_focal_length_ratio = max(opts.max_focal_length_ratio, 2.0 * max(ratios))
        opts.min_focal_length_ratio = min(opts.min_focal_length_ratio, 0.5 * min(ratios))
        out = root / "sparse"
        out.mkdir(exist_ok=True)
        res = pycolmap.triangulate_points(rec, db_path, img_dir, out, options=opts, refine_intrinsics=False)
        pts = list(res.points3D.values())
        if not pts:
            return SparseCloud.empty()
        P = np.array([p.xyz for p in pts], np.float64) * unit + origin
        col = np.array([p.color for p in pts], np.uint8).reshape(-1, 3)
        tl = np.array([p.track.length() for p in pts], np.int64)
        err = np.array([p.error for p in pts], np.float64)
        keep = np.isfinite(P).all(1) & (err <= cfg.max_reproj_error)
        log.info("SfM: %d points (mean track %.2f) from %d verified pairs", keep.sum(), tl[keep].mean() if keep.any() else 0, n_pairs)
        return SparseCloud(P[keep], col[keep], tl[keep], err[keep])
    finally:
        if own_tmp:
            shutil.rmtree(root, ignore_errors=True)
