"""The add-on's pseudo-view path: where it starts, and cameras along it as the user edited it.

:func:`plan_path` lays the path along the acquisition trajectory the command line samples its
pseudo views from (:func:`dibrgs_core.camera.trajectory.classify` of the training cameras): a
closed circle round an orbit, else open polylines along the flight lines and between neighbouring
cameras (with the dense cloud, also along each camera's heading where the trainer samples there).
The add-on draws it as a curve object; when it trains, it evaluates the curve in world
space (Blender does the spline maths, whatever the spline type) and hands the polylines of its
splines to :func:`path_cameras`, which spaces cameras uniformly by arc length. Each looks at the
target (an orbit's look-at Empty) or, without one, takes the orientation of the training cameras
nearest to it (slerped between the two nearest), as the command line's poses between cameras do.
World units and the OpenCV camera convention of :mod:`dibrgs_core.camera.pinhole`; numpy only.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..camera.frame import estimate_up, scene_depth
from ..camera.orbit import Orbit, fit_orbit
from ..camera.pinhole import Camera, look_at
from ..camera.serialize import camera_to_dict
from ..camera.rotations import slerp
from ..camera.trajectory import Segment, Trajectory, TrajectoryKind, classify
from ..common.fileio import write_json


def resample_polyline(points: np.ndarray, n: int, closed: bool) -> np.ndarray:
    """``n`` points spaced uniformly by arc length along a polyline.

    Args:
        points: (M, 3) polyline vertices in order, M >= 1.
        n: number of samples, >= 1.
        closed: the polyline returns from the last vertex to the first. A
            closed path gets samples at ``k * L / n`` (the first is not
            repeated at the end); an open one at ``k * L / (n - 1)`` so both
            end points are included.

    Returns:
        (n, 3) float64 samples. A degenerate polyline (zero length) returns
        its first vertex ``n`` times.
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(P) == 0:
        raise ValueError("resample_polyline: empty polyline")
    if n < 1:
        raise ValueError(f"resample_polyline: n must be >= 1, got {n}")
    if not np.isfinite(P).all():
        raise ValueError("resample_polyline: non-finite vertices")
    if closed:
        P = np.concatenate([P, P[:1]], axis=0)
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg)])
    total = cum[-1]
    if total <= 0.0:
        return np.repeat(P[:1], n, axis=0)
    if closed:
        s = np.arange(n) * (total / n)
    else:
        s = np.linspace(0.0, total, n) if n > 1 else np.zeros(1)
    # Segment index of each sample; zero-length segments are never chosen
    # because searchsorted lands on the last vertex with that arc length.
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    seg_len = seg[idx]
    frac = np.where(seg_len > 0, (s - cum[idx]) / np.where(seg_len > 0, seg_len, 1.0), 0.0)
    return P[idx] + frac[:, None] * (P[idx + 1] - P[idx])


def resample_polylines(polylines: Sequence[np.ndarray], n: int, closed: bool | Sequence[bool]) -> np.ndarray:
    """``n`` points spaced uniformly by arc length over several polylines (a curve's splines).

    One polyline: :func:`resample_polyline`. Several: sample ``k`` sits at arc length
    ``(k + 1/2) L / n`` of their total length ``L``, taken polyline after polyline in order (no
    samples on the jumps between them); ``closed`` is one flag or one per polyline.
    """
    polys, flags = _with_flags(polylines, closed, "resample_polylines")
    if len(polys) == 1:
        return resample_polyline(polys[0], n, flags[0])
    if n < 1:
        raise ValueError(f"resample_polylines: n must be >= 1, got {n}")
    runs = []
    for P, c in zip(polys, flags):
        if len(P) == 0 or not np.isfinite(P).all():
            raise ValueError("resample_polylines: empty polyline or non-finite vertices")
        Q = _closed_up(P, c)
        runs.append((Q, np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(Q, axis=0), axis=1))])))
    lengths = np.array([cum[-1] for _, cum in runs])
    if lengths.sum() <= 0.0:
        return np.repeat(polys[0][:1], n, axis=0)
    starts = np.concatenate([[0.0], np.cumsum(lengths)])
    out = np.empty((n, 3))
    for k, s in enumerate((np.arange(n) + 0.5) * (starts[-1] / n)):
        j = int(np.clip(np.searchsorted(starts, s, side="right") - 1, 0, len(runs) - 1))
        Q, cum = runs[j]
        local = s - starts[j]
        i = int(np.clip(np.searchsorted(cum, local, side="right") - 1, 0, max(len(Q) - 2, 0)))
        seg = cum[i + 1] - cum[i] if len(Q) > 1 else 0.0
        f = (local - cum[i]) / seg if seg > 0 else 0.0
        out[k] = Q[i] if len(Q) == 1 else Q[i] + f * (Q[i + 1] - Q[i])
    return out


def _with_flags(polylines: Sequence[np.ndarray], closed: bool | Sequence[bool],
                who: str) -> tuple[list[np.ndarray], list[bool]]:
    """The polylines as (M, 3) float64 arrays and one closed flag each (``closed``: one for all, or
    one per polyline)."""
    polys = [np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in polylines]
    flags = [bool(closed)] * len(polys) if isinstance(closed, (bool, np.bool_)) else [bool(c) for c in closed]
    if not polys or len(flags) != len(polys):
        raise ValueError(f"{who}: give at least one polyline and one closed flag each")
    return polys, flags


def _closed_up(P: np.ndarray, closed: bool) -> np.ndarray:
    """A closed polyline with its first vertex repeated at the end (one vertex stays as it is)."""
    return np.concatenate([P, P[:1]]) if closed and len(P) > 1 else P


def chain_polylines(polylines: Sequence[np.ndarray], closed: bool | Sequence[bool] = False) -> np.ndarray:
    """One continuous route through several polylines (a fly-through along a curve of several
    splines): the first as given, then again and again the remaining polyline with an end nearest
    to the route's end, reversed when its last point is the nearer; consecutive polylines are
    joined by the straight step between them. A closed polyline is opened at its first vertex."""
    polys, flags = _with_flags(polylines, closed, "chain_polylines")
    polys = [_closed_up(p, c) for p, c in zip(polys, flags)]
    route, rest = [polys[0]], list(polys[1:])
    while rest:
        end = route[-1][-1]
        k = min(range(len(rest)), key=lambda i: min(np.linalg.norm(rest[i][0] - end),
                                                    np.linalg.norm(rest[i][-1] - end)))
        nxt = rest.pop(k)
        route.append(nxt[::-1] if np.linalg.norm(nxt[-1] - end) < np.linalg.norm(nxt[0] - end) else nxt)
    return np.concatenate(route)


def follow_rotation(eye: np.ndarray, cams: Sequence[Camera], up: np.ndarray,
                    segments: Sequence[Segment] | None = None) -> np.ndarray:
    """World-to-camera rotation at ``eye`` that follows the cameras ``cams`` as the command line's
    poses between cameras do: the trajectory segment nearest to ``eye`` across ``up`` (default:
    :func:`~dibrgs_core.camera.trajectory.classify`'s segments, else each camera's nearest
    neighbour), its end cameras' rotations slerped at ``eye``'s place along it, clamped to the
    segment (past a line's end camera: that camera's rotation). Consecutive segments share their
    camera, so the rotation is continuous along a line and across its cameras."""
    cams = list(cams)
    if len(cams) == 1:
        return cams[0].R.copy()
    u = np.asarray(up, np.float64) / max(np.linalg.norm(up), 1e-300)
    C = np.stack([c.center for c in cams])
    C = C - np.outer(C @ u, u)
    e = np.asarray(eye, np.float64) - (np.asarray(eye, np.float64) @ u) * u
    segs = list(segments) if segments else _follow_segments(cams, u)
    best = (np.inf, 0, 0, 0.0)
    for s in segs:
        ab = C[s.b] - C[s.a]
        L2 = float(ab @ ab)
        t = float(np.clip((e - C[s.a]) @ ab / L2, 0.0, 1.0)) if L2 > 0 else 0.0
        d = float(np.linalg.norm(C[s.a] + t * ab - e))
        if d < best[0]:
            best = (d, s.a, s.b, t)
    _, a, b, t = best
    return cams[a].R.copy() if a == b else slerp(cams[a].R, cams[b].R, t)


def _follow_segments(cams: Sequence[Camera], up: np.ndarray) -> list[Segment]:
    """The segments :func:`follow_rotation` projects onto: the trajectory's, or (an orbit, whose
    poses look at its target and have none) each camera and its nearest neighbour."""
    segs = [s for s in classify(cams, up=up).segments if s.a != s.b]
    if segs:
        return segs
    C = np.stack([c.center for c in cams])
    D = np.linalg.norm(C[:, None] - C[None], axis=-1) + np.diag(np.full(len(cams), np.inf))
    return [Segment(i, int(np.argmin(D[i]))) for i in range(len(cams))]


def path_cameras(points: np.ndarray | Sequence[np.ndarray], n: int, target: Sequence[float] | None,
                 up: Sequence[float], like: Camera, closed: bool | Sequence[bool], prefix: str = "pseudo",
                 follow: Sequence[Camera] = ()) -> list[Camera]:
    """``n`` cameras spaced along the path by arc length.

    ``points`` is one (M, 3) polyline or a list of them (a curve's splines; see
    :func:`resample_polylines`). With a ``target`` every camera looks at it, ``up`` (the scene's
    up axis) appearing up in the images; a sample that coincides with the target is moved off
    it along ``up`` by a tiny amount so the look-at is defined. Without one every camera takes
    :func:`follow_rotation` of the cameras ``follow`` (the training cameras). ``like`` gives K,
    image size and depth range. Names are ``f"{prefix}_{k:03d}"``.
    """
    single = points.ndim != 3 if isinstance(points, np.ndarray) else not len(points) or np.ndim(points[0]) != 2
    eyes = resample_polylines([points] if single else points, n, closed)
    up = np.asarray(up, dtype=np.float64)
    if target is None and not len(follow):
        raise ValueError("path_cameras: give a target to look at or cameras to follow")
    cams = []
    if target is not None:
        target = np.asarray(target, dtype=np.float64)
        scale = max(float(np.abs(eyes).max(initial=0.0)), float(np.abs(target).max()), 1.0)
    else:
        follow = list(follow)
        segs = _follow_segments(follow, up) if len(follow) > 1 else None
    for k, eye in enumerate(eyes):
        if target is not None:
            if np.linalg.norm(eye - target) < 1e-9 * scale:
                eye = eye + 1e-6 * scale * up / max(np.linalg.norm(up), 1e-300)
            w2c = look_at(eye, target, up)
        else:
            w2c = np.eye(4)
            w2c[:3, :3] = follow_rotation(eye, follow, up, segs)
            w2c[:3, 3] = -w2c[:3, :3] @ eye
        cams.append(Camera(K=like.K.copy(), w2c=w2c, width=like.width, height=like.height,
                           name=f"{prefix}_{k:03d}", depth_range=like.depth_range))
    return cams


@dataclass
class PathPlan:
    """Where the add-on's pseudo-view path starts (:func:`plan_path`).

    Attributes:
        kind, reason: the training cameras' trajectory as the trainer classifies it
            (:func:`~dibrgs_core.camera.trajectory.classify` with their own up axis).
        up: unit up axis of the scene (world, from all its cameras).
        orbit: the circle to draw (kind ``orbit``, or another kind that gives no line to draw),
            fitted to the scene's Track cameras when it has three or more, else to the training
            cameras; cameras on it look at its target.
        polylines: otherwise, the open polylines to draw (world points in order): each fitted
            flight line through its cameras, continued past its end cameras as the command line's
            sampling is, each pair of neighbouring cameras not on one line, and the line along
            each camera's heading where the trainer samples one (all the scene's cameras at one
            place: a polyline at that place); cameras along them follow the training cameras'
            orientation.
    """

    kind: TrajectoryKind
    reason: str
    up: np.ndarray
    orbit: Orbit | None = None
    polylines: list[np.ndarray] | None = None


def plan_path(train: Sequence[Camera], track: Sequence[Camera] = (), views: Sequence[Camera] = (),
              points: np.ndarray | None = None) -> PathPlan:
    """The pseudo-view path along the acquisition trajectory of the training cameras ``train``
    (``views``: all the scene's cameras, for the up axis; ``track``: a LEVIR-NVS Track;
    ``points``: the dense cloud (N, 3, world), when there is one). With the cloud, the scene's
    depth is known and one photo a strip also gives a line along each camera's heading, as the
    trainer samples it; without, the line across the strips only."""
    train, track, views = list(train), list(track), list(views)
    cams = train or views
    if not cams:
        raise ValueError("plan_path needs at least one camera")
    up, _ = estimate_up(views or cams)
    # as the trainer does: the training cameras' own up axis, the cloud's depth
    depth = scene_depth(points, cams) if points is not None else None
    traj = classify(cams, scene_depth=depth)
    lines = [] if traj.kind == "orbit" else _trajectory_polylines(traj, cams)
    if lines:
        return PathPlan(traj.kind, traj.reason, up, polylines=lines)
    circle = track if len(track) >= 3 else (cams if len(cams) >= 3 else views)
    C = np.stack([c.center for c in circle])
    if len(circle) < 2 or np.ptp(C, axis=0).max() <= 1e-9 * max(float(np.abs(C).max()), 1e-300):
        # One camera position in the whole scene: nothing to go round; the path is that place.
        return PathPlan(traj.kind, f"{traj.reason}; the path is the camera's position", up,
                        polylines=[np.stack([C[0], C[0]])])
    reason = traj.reason if traj.kind == "orbit" else f"{traj.reason}; no line to draw, a circle instead"
    return PathPlan(traj.kind, reason, up, orbit=fit_orbit(circle, up=up))


def _trajectory_polylines(traj: Trajectory, cams: Sequence[Camera]) -> list[np.ndarray]:
    """Open polylines of a ``strips`` or ``free`` trajectory (see :class:`PathPlan`); segments of
    zero length (cameras at one position) are left out."""
    C = np.stack([c.center for c in cams])
    on_line = set()
    out = []
    ends = {}
    for s in traj.segments:
        if s.t1 > 1.0:  # a line continued past its end camera s.b
            ends[s.b] = C[s.a] + s.t1 * (C[s.b] - C[s.a])
    for line in traj.lines:
        if len(line) < 2:
            continue
        pts = [C[i] for i in line]
        pts = ([ends[line[0]]] if line[0] in ends else []) + pts + ([ends[line[-1]]] if line[-1] in ends else [])
        out.append(np.stack(pts))
        on_line.update(zip(line[:-1], line[1:]))
    for s in traj.segments:
        if s.direction is not None:  # along camera s.a's heading
            out.append(np.stack([s.point(C, s.t0), s.point(C, s.t1)]))
        elif s.t1 <= 1.0 and (s.a, s.b) not in on_line and (s.b, s.a) not in on_line and s.a != s.b:
            out.append(np.stack([C[s.a], C[s.b]]))
    scale = max(float(np.abs(C).max()), 1e-300)
    return [p for p in out if np.linalg.norm(np.diff(p, axis=0), axis=1).sum() > 1e-9 * scale]


def orbit_control_points(orbit: Orbit, n: int = 8) -> np.ndarray:
    """(n, 3) points on the fitted orbit, evenly spaced, starting at angle 0 (view 1).

    The add-on turns them into a cyclic curve with automatic handles; 8
    points keep the curve within a fraction of a percent of the circle.
    """
    if n < 3:
        raise ValueError("an orbit curve needs at least 3 control points")
    return orbit.point(np.arange(n) * (2.0 * np.pi / n))


def write_camera_list(path: str | Path, cams: Sequence[Camera], origin: Sequence[float] | None = None) -> Path:
    """Write cameras as a JSON camera list (``camera_to_dict`` format), atomically; cameras relative
    to ``origin`` (a scene description's) are written in the scene files' own frame."""
    path = Path(path)
    if origin is not None and np.any(origin):
        cams = [c.translated(origin) for c in cams]
    write_json(path, [camera_to_dict(c) for c in cams])
    return path
