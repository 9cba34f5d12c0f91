"""The scene frame a set of cameras implies: up axis, nadir angle, horizontal frame, look-at point,
and the depth of a cloud in front of them.

Aerial views are not assumed to use +Z as up: up comes from the cameras themselves (the
opposite of their mean viewing direction, refined where they are held level; see
:func:`estimate_up`). OpenCV cameras (:mod:`.pinhole`), world units. NumPy only.
"""
from __future__ import annotations

from typing import Iterable, Sequence

import numpy as np

from .pinhole import Camera


#: Cameras count as held level (no roll) when their image x axes leave a common plane by at most
#: this RMS angle (degrees): gimbals and survey mounts keep the image's x axis horizontal.
LEVEL_ROLL_DEG = 5.0
#: :attr:`Camera.span <.pinhole.Camera.span>` of the lens the paper's lengths and angles are taken
#: for: a 35 mm lens on a 36 mm sensor (about 54 degrees across), as the LEVIR-like generated scenes.
REFERENCE_SPAN = 36.0 / 35.0
#: The x axes fix up on their own when they spread this far out of one direction (RMS angle,
#: degrees): the cameras face different headings (an orbit, a free flight).
HEADING_SPREAD_DEG = 10.0


def estimate_up(cams: Iterable[Camera]) -> tuple[np.ndarray, float]:
    """Scene up axis from the cameras, and how much their viewing directions agree.

    The first estimate is the opposite of the mean viewing direction. Where the cameras are held
    level (image x axes horizontal within :data:`LEVEL_ROLL_DEG`) and face different headings, up
    is the axis perpendicular to every x axis instead (exact for an orbit, where a few cameras'
    mean direction leans towards their side of the circle). Level cameras that all face one
    heading leave up free to turn about that axis: the first estimate is kept, less any part of
    it along the axis (roll noise). So a camera pitched forward on a grid or a corridor flown at
    one heading reads as a nadir camera: from the poses alone that flight cannot be told from a
    nadir camera climbing a slope at the pitch angle, and nadir photos are what mapping flights
    take.

    Returns ``(up (3,), confidence)``: confidence is the length of the mean unit viewing
    direction in [0, 1]; near 0 means the cameras look in all directions and the up axis is
    ambiguous.
    """
    cams = list(cams)
    dirs = np.stack([c.view_dir for c in cams])
    m = dirs.mean(axis=0)
    n = float(np.linalg.norm(m))
    if n < 1e-12:
        return np.array([0.0, 0.0, 1.0]), 0.0
    u_view = -m / n
    X = np.stack([c.R[0] / np.linalg.norm(c.R[0]) for c in cams])  # image x axes in world
    w, V = np.linalg.eigh(X.T @ X / len(X))  # ascending: V[:, 0] the axis the x axes avoid most
    if w[0] > np.sin(np.radians(LEVEL_ROLL_DEG)) ** 2:
        return u_view, n  # not held level: the x axes say nothing about up
    if w[1] > np.sin(np.radians(HEADING_SPREAD_DEG)) ** 2:
        up = V[:, 0]
    else:  # one heading: up lies across the common x axis
        P = V[:, :2]
        up = P @ (P.T @ u_view)
    up = up / max(float(np.linalg.norm(up)), 1e-300)
    return (up if up @ u_view >= 0 else -up), n


def nadir_angle_deg(cams: Sequence[Camera], up: np.ndarray | None = None) -> float:
    """Angle in degrees between the mean viewing direction and straight down."""
    if up is None:
        up, _ = estimate_up(cams)
    dirs = np.stack([c.view_dir for c in cams])
    ang = np.degrees(np.arccos(np.clip(dirs @ -up, -1.0, 1.0)))
    return float(ang.mean())


def up_frame(up: np.ndarray) -> np.ndarray:
    """3x3 rotation whose rows are (e1, e2, up): world -> (horizontal, horizontal, height)."""
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    ref = np.eye(3)[np.argmin(np.abs(up))]
    e1 = np.cross(ref, up)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    return np.stack([e1, e2, up])


def look_at_target(cams: Sequence[Camera]) -> np.ndarray:
    """Least-squares point closest to all optical axes (the orbit's look-at point)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for c in cams:
        d = c.view_dir
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c.center
    if np.linalg.cond(A) > 1e12:  # all axes parallel: no unique point
        return np.mean([c.center + c.view_dir for c in cams], axis=0)
    return np.linalg.solve(A, b)


#: Defaults of :func:`near_nadir` (the geometry stage's ``InitConfig`` and the plane sweep use them).
MAX_NADIR_DEG = 60.0
MIN_UP_CONFIDENCE = 0.5


def near_nadir(cams: Sequence[Camera], max_nadir_deg: float = MAX_NADIR_DEG,
               min_up_confidence: float = MIN_UP_CONFIDENCE) -> tuple[bool, str]:
    """Whether ``cams`` look near straight down with a clear up axis, and why.

    Near-nadir: the up axis the cameras imply (:func:`estimate_up`) has a confidence of at
    least ``min_up_confidence`` and their mean angle from straight down is at most
    ``max_nadir_deg`` degrees.
    """
    up, conf = estimate_up(cams)
    nadir_deg = nadir_angle_deg(cams, up)
    if conf < min_up_confidence:
        return False, f"the up axis is ambiguous (camera agreement {conf:.2f} < {min_up_confidence})"
    if nadir_deg > max_nadir_deg:
        return False, f"cameras are not near-nadir (mean {nadir_deg:.1f} deg from straight down > {max_nadir_deg})"
    return True, f"near-nadir cameras ({nadir_deg:.1f} deg from straight down, up agreement {conf:.2f})"


def central_camera(cams: Sequence[Camera]) -> Camera:
    """The camera nearest to the mean camera centre (a representative viewpoint of a set)."""
    c = np.mean([x.center for x in cams], 0)
    return min(cams, key=lambda x: float(np.linalg.norm(x.center - c)))


def scene_depth(points: np.ndarray, cams: Sequence[Camera]) -> float | None:
    """Median z-depth (world units) of ``points`` (N, 3, world) in front of the cameras ``cams``
    (at most about 5,000 points a camera), or None when none is in front: the ``scene_depth``
    of :func:`~.trajectory.classify`."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    zs = [c.world_to_cam(pts[:: max(1, len(pts) // 5000)])[:, 2] for c in cams] if len(pts) else []
    z = np.concatenate(zs) if zs else np.zeros(0)
    z = z[np.isfinite(z) & (z > 0)]
    return float(np.median(z)) if len(z) else None


def span_factor(cams: Iterable[Camera]) -> float:
    """The cameras' median :attr:`~.pinhole.Camera.span` over :data:`REFERENCE_SPAN`: how much more
    ground (or less: a telephoto or satellite lens, about 0.01) a view covers at a given depth than
    the reference lens does. Lengths that stand for a share of the scene and tolerances on relative
    depth are taken in proportion, so a narrow view is not treated as a wide view of a larger scene.
    Exactly 1 for the reference lens (the division's rounding would move every threshold by a bit)."""
    span = float(np.median([c.span for c in cams]))
    return 1.0 if np.isclose(span, REFERENCE_SPAN, rtol=1e-9, atol=0.0) else span / REFERENCE_SPAN


def overlap_distance(cams: Sequence[Camera]) -> float:
    """Distance to the scene if neighbouring photos overlapped by half, world units (a guess where
    nothing better is known: no SfM points, no depth ranges): the median nearest-neighbour camera
    spacing is then half the footprint, ``d * mean(W, H) / f``. 1 for a single camera."""
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
