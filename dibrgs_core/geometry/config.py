"""Options of the geometry initialisation (paper "Initialization with Dense Depth Priors" and
"Implementation Details"); lengths in paper (LEVIR-NVS) units unless a field says otherwise.

Units. The paper's thresholds (eps_xy 0.1, eps_z 1.0, voxel 1.0, height-map cell 10) are in
LEVIR-NVS units, where the training cameras are about ``LEVIR_REFERENCE_DEPTH`` = 115 units from
the scene (the paper's MAE / Abs Rel ratio, 3.16 / 0.0273). ``InitConfig.scale = None`` scales
them by the scene's reference distance x the lens's span / 115 (:mod:`.scene_geometry`) so a scene
in other units (or a generated one, or one seen through a telephoto or satellite lens) gets the
same relative thresholds; a number overrides it. The sweep's height range and its relative depth
tolerances (``consistency_tol``, ``speckle_tol``) are taken for the reference lens and multiplied by
the span as well (:func:`~dibrgs_core.camera.frame.span_factor`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ..camera.frame import MAX_NADIR_DEG, MIN_UP_CONFIDENCE
from ..common.modes import DepthMap, DepthPrior, Refine, SweepPlanes, Switch

LEVIR_REFERENCE_DEPTH = 115.0
#: The stage name in reports.
STAGE = "init"


@dataclass
class SfmConfig:
    """Options of the sparse reconstruction.

    Attributes:
        max_num_features: SIFT features per image.
        keep_two_view_tracks: keep points seen by only two views (with three
            sparse views most tracks have length two).
        min_angle_deg: minimum triangulation angle.
        max_reproj_error: reprojection error (px) above which points are dropped.
        seed: COLMAP's RANSAC and triangulation seed (its default, -1, seeds from the clock).
        max_neighbours: each photo is matched with at most this many others, those whose camera
            centres are nearest (as COLMAP's spatial matcher does with GPS positions); with this
            many others or fewer, every pair (0 = always every pair: 81 photos at 512 px, 3,240
            pairs, 3 minutes; the count grows with the square of the photos).

    COLMAP matches and triangulates on one thread: with two (in triangulation, or in extraction
    and matching) the same views gave 56, 68, 75 or 97 points from one run to the next, about one
    run in twelve; on one, 40 of 40 runs on a loaded machine were equal. SIFT extraction shares
    the photos out over torch's thread count and they are renumbered in name order afterwards
    (the same points as on one thread, to the bit).
    """

    max_num_features: int = 8192
    keep_two_view_tracks: bool = True
    min_angle_deg: float = 1.5
    max_reproj_error: float = 4.0
    seed: int = 0
    max_neighbours: int = 20


@dataclass
class MvsConfig:
    """Plane-sweep options.

    Attributes:
        num_depths: depth planes between near and far (uniform in 1/depth).
        window: NCC window side in pixels (odd).
        min_ncc: pixels whose best NCC is lower are marked invalid.
        min_confidence: pixels whose peak-ratio confidence is lower are invalid.
        min_texture_rel: minimum reference-window standard deviation for NCC
            to be meaningful, as a fraction of the image's median window
            standard deviation (a fixed level in image units would reject
            more of a darker photo: not gain-invariant).
        consistency_tol: geometric check between views: a depth is kept when
            it agrees, within this relative tolerance, with the depth another
            view estimated at its reprojection.
        min_consistent_views: how many other views must agree (0 disables
            the check).
        max_reproj_px: forward-backward reprojection error (pixels of the
            swept resolution) allowed by the consistency check.
        max_size: views whose longer side exceeds this are swept at a
            reduced resolution (speed on CPU) and the depth is upsampled
            (nearest) to the full size; 0 = always full size.
        plane_chunk: planes evaluated per batch (memory / speed trade-off).
        planes: ``height`` (horizontal planes in the up frame the cameras give),
            ``fronto`` (fronto-parallel) or ``auto`` (height planes for
            near-nadir cameras, see :func:`sweep_up`).
        prefilter: 3x3 box blur of the images before matching (anti-aliasing;
            wide baselines see fine ground texture at very different scales).
        height_below, height_above: height planes span from ``height_below``
            below to ``height_above`` above the ground (the cameras' look-at
            point), in units of the flying height above it (0 = the range the
            cameras' depth ranges allow).
        max_nadir_deg, min_up_confidence: ``auto`` uses height planes when the
            cameras are near-nadir by these thresholds (:func:`~dibrgs_core.camera.frame.near_nadir`).
        sgm_paths: semi-global aggregation of the cost volume along 4 or 8
            image directions before the winner-take-all (0 = off; other
            values are refused); see
            :func:`semi_global`. On the generated 128x128 LEVIR-like city it
            lifts DIBR-GS held-out PSNR by 0.7 dB over the plain sweep.
        sgm_p1, sgm_p2: its penalties (in 1 - NCC units) for moving to a
            neighbouring plane and for jumping to any plane.
        speckle_px: after the sweep, connected regions of fewer pixels (of the
            swept resolution) whose neighbouring depths agree within
            ``speckle_tol`` are dropped (0 = off): tree crowns, water and
            moving objects match by chance in small scattered patches that a
            two-view consistency check lets through.
        speckle_tol: relative depth step that still connects two neighbouring pixels.
        max_sources: each view is swept against at most this many others, those that see
            most of it from a useful angle (:mod:`~dibrgs_core.geometry.view_selection`), and
            checked for consistency against the same ones; with this many others or fewer,
            all of them (0 = always all: time grows with the square of the view count). COLMAP
            takes up to 20; 8 keeps a survey of 80 photos at minutes on two CPU cores.
    """

    num_depths: int = 96
    window: int = 7
    min_ncc: float = 0.6
    min_confidence: float = 0.1
    min_texture_rel: float = 0.15
    plane_chunk: int = 8
    consistency_tol: float = 0.02
    min_consistent_views: int = 1
    max_reproj_px: float = 1.0
    max_size: int = 256
    planes: SweepPlanes = "auto"
    height_below: float = 0.1
    height_above: float = 0.6
    prefilter: bool = True
    max_nadir_deg: float = MAX_NADIR_DEG
    min_up_confidence: float = MIN_UP_CONFIDENCE
    sgm_paths: int = 4
    sgm_p1: float = 0.1
    sgm_p2: float = 1.0
    speckle_px: int = 50
    speckle_tol: float = 0.01
    max_sources: int = 8


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
        max_side: long side (pixels) the stage works at: larger training photos
            are area-averaged down to it with their cameras (0: as they are). A
            drone's 8-20 MP photos back-project to tens of millions of points
            (16 GB, 3.4 min for three 8 MP photos) that the voxel grid then
            thins to a few tens of thousands; at 1,024 px a pixel is still
            finer than the voxel.
        max_overlap_pairs: the overlap removal compares every two points closer than
            ``eps_xy`` horizontally; their number grows with the square of the cloud's density
            (81 views of one ground at 512 px: over a billion, 21 GB). Above about this many
            (estimated from a grid of side ``eps_xy``), the fused cloud is thinned first to a
            random share that stays within it: redundant points many views measured, far finer
            than the ``voxel`` the cloud is reduced to afterwards. Three photos stay far below
            (0.4-3.4 million), all nine of brighton_north at 953x536 too (18 million).
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
    max_overlap_pairs: int = 40_000_000
    voxel: float = 1.0
    height_cell: float = 10.0
    height_percentile: float = 95.0
    height_relax: float = 1.1
    height_margin: float = 1.0
    max_nadir_deg: float = MAX_NADIR_DEG
    min_up_confidence: float = MIN_UP_CONFIDENCE
    min_sfm_points: int = 20
    dense_sfm_ratio: float = 0.05
    complete: Switch = "auto"
    completion_confidence: float = 0.25
    completion_cell_px: float = 4.0
    completion_voxel: float = 2.0
    max_side: int = 1024
    sfm: SfmConfig = field(default_factory=SfmConfig)
    mvs: MvsConfig = field(default_factory=MvsConfig)
