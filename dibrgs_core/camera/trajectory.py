"""The acquisition trajectory of a few cameras: its kind, and camera poses along it.

The paper samples pseudo views "along the acquisition trajectory of the input
views ... between existing cameras". Real acquisitions are not all circles:

* ``orbit``: the cameras lie on a circle and look towards its axis (LEVIR-NVS,
  the generated scenes; an oblique orbit round a site);
* ``strips``: the camera centres lie on one straight line (a corridor, or one
  photo from each strip of a mapping flight: then the cameras face across the
  line, at least two thirds of them, and the strips run along their headings)
  or on parallel straight lines
  with at least two cameras each (a mapping grid);
* ``free``: anything else.

:func:`classify` finds the kind and says why; :func:`sample_poses` draws
cameras on the trajectory: on the circle for an orbit, along the fitted
lines (continued half a camera spacing past their end cameras) and between
neighbouring cameras of adjacent lines for strips, between neighbouring
cameras otherwise; for one photo a strip also along each camera's heading (half
the image's ground extent either way; half the draws). Positions are interpolated, rotations slerped, and each
pose is jittered a little in position (a fraction of the camera spacing)
and look direction (degrees), so nothing depends on the scene's units.

OpenCV cameras (:mod:`.pinhole`), world units, up from
:func:`.frame.estimate_up`. NumPy only (Blender's Python imports it).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np

from .frame import estimate_up, span_factor, up_frame
from .orbit import Orbit, fit_orbit
from .pinhole import Camera, look_at
from .rotations import axis_angle, slerp

#: Kinds of acquisition trajectory :func:`classify` tells apart.
TrajectoryKind = Literal["orbit", "strips", "free"]

#: Camera centres whose horizontal spread across their main direction is at most this
#: fraction of the spread along it lie on one straight line.
LINE_TOL = 0.1
#: An orbit's cameras look towards its axis: the horizontal part of each viewing direction
#: points at the circle's centre within this angle (degrees) ...
ORBIT_AIM_DEG = 30.0
#: ... once the cameras look at least this far off nadir (degrees); nadir cameras on a
#: circle need :data:`ORBIT_MIN_NADIR_CAMS` of them and a small fit residual instead.
ORBIT_MIN_TILT_DEG = 3.0
ORBIT_MIN_NADIR_CAMS = 5
#: Largest RMS distance from the fitted circle, as a fraction of its radius.
ORBIT_RMS_TOL = 0.1


@dataclass
class Segment:
    """Poses between camera ``a`` and camera ``b``: position ``C_a + t (C_b - C_a)`` for ``t`` in
    ``[t0, t1]`` (beyond [0, 1] continues the line past an end camera), rotation slerped at
    ``clip(t, 0, 1)``. With ``direction`` (world vector; then ``b == a``): position
    ``C_a + t direction``, camera ``a``'s rotation. ``weight`` scales the segment's share of the
    sampled poses (its length times the weight)."""

    a: int
    b: int
    t0: float = 0.0
    t1: float = 1.0
    direction: np.ndarray | None = None
    weight: float = 1.0

    def step(self, C: np.ndarray) -> np.ndarray:
        """Displacement for ``t`` from 0 to 1 (``C``: the cameras' centres)."""
        return self.direction if self.direction is not None else C[self.b] - C[self.a]

    def point(self, C: np.ndarray, t: float) -> np.ndarray:
        """Position at ``t``."""
        return C[self.a] + t * self.step(C)

    def length(self, C: np.ndarray) -> float:
        """Length of the segment from ``t0`` to ``t1`` (world units)."""
        return float(np.linalg.norm(self.step(C))) * (self.t1 - self.t0)


@dataclass
class Trajectory:
    """What :func:`classify` found.

    Attributes:
        kind: orbit, strips or free.
        reason: one sentence: why this kind, with the measured figures.
        up: unit up axis of the scene (world).
        spacing: median distance from a camera to its nearest neighbour (world units).
        orbit: the fitted circle (kind ``orbit`` only).
        lines: camera indices of each fitted line, ordered along it (kind ``strips``).
        segments: where :func:`sample_poses` draws poses between cameras (not used for an orbit).
    """

    kind: TrajectoryKind
    reason: str
    up: np.ndarray
    spacing: float
    orbit: Orbit | None = None
    lines: list[list[int]] = field(default_factory=list)
    segments: list[Segment] = field(default_factory=list)

    def describe(self) -> dict:
        """JSON-friendly summary (for reports)."""
        return {"kind": self.kind, "reason": self.reason, "spacing": self.spacing, "lines": self.lines,
                "orbit": None if self.orbit is None else self.orbit.to_dict()}


# -- Classification -----------------------------------------------------------
def _nn_spacing(P: np.ndarray, same: float = 0.0) -> float:
    """Median distance from a position to its nearest other position (positions at most ``same``
    apart count as one: two photos from one place do not make the spacing 0); 0 when all coincide."""
    D = np.linalg.norm(P[:, None] - P[None], axis=-1)
    D[D <= same] = np.inf  # the diagonal too
    s = float(np.median(D.min(1)))
    return s if np.isfinite(s) and s > 0 else 0.0


def _line_fit(P: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Main direction (2,) of horizontal points, their spread along it and across it (RMS)."""
    Q = P - P.mean(0)
    _, s, vt = np.linalg.svd(Q, full_matrices=False)
    n = len(P)
    along = float(s[0]) / np.sqrt(n)
    across = float(s[1]) / np.sqrt(n) if len(s) > 1 else 0.0
    return vt[0], along, across


def _orbit_evidence(cams: Sequence[Camera], orbit: Orbit, F: np.ndarray, P: np.ndarray) -> tuple[bool, str]:
    """Whether the cameras sit on ``orbit`` and look towards its axis, and the figures."""
    rel_rms = orbit.rms / max(orbit.radius, 1e-300)
    if len(cams) >= 4 and rel_rms > ORBIT_RMS_TOL:
        return False, f"the circle through them misses them by {100 * rel_rms:.0f}% of its radius"
    c2 = (orbit.center @ F.T)[:2]
    dirs = np.stack([c.view_dir for c in cams]) @ F.T
    horiz = dirs[:, :2]
    tilt = np.degrees(np.arcsin(np.clip(np.linalg.norm(horiz, axis=1), 0, 1)))
    if tilt.min() >= ORBIT_MIN_TILT_DEG:
        inward = c2 - P
        cosang = (horiz * inward).sum(1) / np.maximum(np.linalg.norm(horiz, axis=1) * np.linalg.norm(inward, axis=1),
                                                      1e-300)
        worst = float(np.degrees(np.arccos(np.clip(cosang.min(), -1, 1))))
        if worst <= ORBIT_AIM_DEG:
            return True, (f"{len(cams)} cameras {tilt.mean():.0f} deg off nadir on a circle of radius "
                          f"{orbit.radius:.3g} look towards its axis (worst {worst:.0f} deg off)")
        return False, f"the cameras do not look towards the axis of the circle through them ({worst:.0f} deg off)"
    if len(cams) >= ORBIT_MIN_NADIR_CAMS:
        return True, (f"{len(cams)} near-nadir cameras lie on a circle of radius {orbit.radius:.3g} "
                      f"(RMS {100 * rel_rms:.1f}% of it)")
    return False, (f"{len(cams)} near-nadir cameras (< {ORBIT_MIN_NADIR_CAMS}) off any straight line: a circle "
                   "through them is no evidence of an orbit")


def _parallel_lines(P: np.ndarray, spacing: float) -> tuple[list[list[int]], float] | None:
    """Split horizontal camera positions into parallel straight lines of >= 2 cameras each.

    Candidate directions are those from each camera to its nearest neighbour; a direction
    works when the cameras' offsets across it fall into groups of >= 2 separated by more
    than a quarter of the spacing, each group straight within :data:`LINE_TOL` of the
    spacing. Returns the lines (indices ordered along them) and the worst offset, or None.
    """
    n = len(P)
    D = np.linalg.norm(P[:, None] - P[None], axis=-1)
    np.fill_diagonal(D, np.inf)
    best = None
    for i in range(n):
        d = P[int(np.argmin(D[i]))] - P[i]
        d = d / max(np.linalg.norm(d), 1e-300)
        nrm = np.array([-d[1], d[0]])
        off = P @ nrm
        order = np.argsort(off)
        groups, cur = [], [int(order[0])]
        for a, b in zip(order[:-1], order[1:]):
            if off[b] - off[a] > 0.25 * spacing:
                groups.append(cur)
                cur = []
            cur.append(int(b))
        groups.append(cur)
        if len(groups) < 2 or min(len(g) for g in groups) < 2:
            continue
        worst = max(float(np.abs(off[g] - off[g].mean()).max()) for g in groups)
        if worst > LINE_TOL * spacing:
            continue
        lines = [sorted(g, key=lambda k: float(P[k] @ d)) for g in groups]
        # A flight grid is regular: cameras along the lines, and the lines themselves, about
        # evenly spaced (chords of a circle pair up in parallel but at every length).
        steps = np.array([np.linalg.norm(P[b] - P[a]) for ln in lines for a, b in zip(ln[:-1], ln[1:])])
        gaps = np.diff(np.sort([float(np.mean(off[g])) for g in groups]))
        if steps.max() > 2.0 * steps.min() or gaps.max() > 2.0 * gaps.min():
            continue
        if best is None or worst < best[1]:
            best = (lines, worst)
    return best


def _segments_along(lines: list[list[int]], P: np.ndarray, extend: float) -> list[Segment]:
    """Consecutive cameras of each line, the end segments continued ``extend`` spacings past the ends."""
    segs = []
    for line in lines:
        for a, b in zip(line[:-1], line[1:]):
            segs.append(Segment(a, b))
        if len(line) >= 2:
            first = np.linalg.norm(P[line[1]] - P[line[0]])
            last = np.linalg.norm(P[line[-1]] - P[line[-2]])
            spc = float(np.median([np.linalg.norm(P[b] - P[a]) for a, b in zip(line[:-1], line[1:])]))
            segs.append(Segment(line[1], line[0], 1.0, 1.0 + extend * spc / max(first, 1e-300)))
            segs.append(Segment(line[-2], line[-1], 1.0, 1.0 + extend * spc / max(last, 1e-300)))
    return segs


def _neighbour_pairs(P: np.ndarray) -> list[tuple[int, int]]:
    """Edges of the minimum spanning tree of the positions plus each one's nearest neighbour."""
    n = len(P)
    D = np.linalg.norm(P[:, None] - P[None], axis=-1)
    pairs = set()
    inside, rest = [0], set(range(1, n))
    while rest:  # Prim
        a, b = min(((i, j) for i in inside for j in rest), key=lambda e: D[e])
        pairs.add((min(a, b), max(a, b)))
        inside.append(b)
        rest.discard(b)
    Dn = D + np.diag(np.full(n, np.inf))
    for i in range(n):
        j = int(np.argmin(Dn[i]))
        pairs.add((min(i, j), max(i, j)))
    return sorted(pairs)


def _headings_across(cams: Sequence[Camera], F: np.ndarray, d: np.ndarray,
                     scene_depth: float | None) -> tuple[list[np.ndarray], int] | None:
    """For cameras on one line (horizontal direction ``d`` in frame ``F``): when two thirds of them face
    across it (heading = image up, horizontal, within 30 degrees of square to the line), the world vector
    from each camera to half its image's ground extent along its heading (``scene_depth`` x its half
    extent that way over the focal length) and how many faced; else None (no depth known either). Strips
    are parallel: a camera not facing across (a photo stored turned) takes the heading square to the line."""
    if not scene_depth or not np.isfinite(scene_depth) or scene_depth <= 0:
        return None
    out, facing = [], 0
    for c in cams:
        hh, right = ((-c.R[1]) @ F.T)[:2], (c.R[0] @ F.T)[:2]  # image up and right in (e1, e2)
        norm = float(np.linalg.norm(hh))
        faces = norm >= 0.5 and abs(float(hh @ d)) / norm <= np.sin(np.radians(30.0))
        facing += faces
        head = hh / norm if faces else np.array([-d[1], d[0]])
        # the image's half extent along the heading: its height where image up points that way
        up = abs(float(head @ hh)) >= abs(float(head @ right))
        half = 0.5 * c.height / float(c.K[1, 1]) if up else 0.5 * c.width / float(c.K[0, 0])
        out.append(np.array([head[0], head[1], 0.0]) @ F * (half * scene_depth))
    return (out, facing) if 3 * facing >= 2 * len(cams) else None


def classify(cams: Sequence[Camera], up: np.ndarray | None = None, extend: float = 0.5,
             scene_depth: float | None = None) -> Trajectory:
    """The kind of trajectory the camera centres follow, and why.

    Args:
        cams: the training cameras (at least 1).
        up: scene up axis (default :func:`.frame.estimate_up`).
        extend: strips are continued this many camera spacings past their end cameras.
        scene_depth: typical distance from the cameras to the scene (world units); a single
            camera (or cameras at one position) has no spacing, so a quarter of the ground a view
            covers there (x :func:`.frame.span_factor`) stands in for it (default 1).
    """
    cams = list(cams)
    if not cams:
        raise ValueError("classify needs at least one camera")
    if up is None:
        up, _ = estimate_up(cams)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    F = up_frame(up)
    C = np.stack([c.center for c in cams])
    P = (C @ F.T)[:, :2]
    n = len(cams)
    known = scene_depth and np.isfinite(scene_depth) and scene_depth > 0
    stand_in = 0.25 * scene_depth * span_factor(cams) if known else 1.0
    spacing = _nn_spacing(P, 1e-9 * float(np.abs(C).max())) if n > 1 else 0.0
    # Positions equal up to rounding (of the coordinates, or against the scene's depth) coincide.
    if spacing <= max(1e-9 * float(np.abs(C).max()), 1e-6 * stand_in if scene_depth else 0.0):
        return Trajectory("free", f"{'a single camera' if n == 1 else 'the cameras share one position'}: "
                          "poses are jittered around it", up, stand_in, segments=[Segment(0, 0)])
    if n == 2:
        return Trajectory("strips", "two cameras: the line through them", up, spacing, lines=[[0, 1]],
                          segments=_segments_along([[0, 1]], P, extend))
    d, along, across = _line_fit(P)
    if across <= LINE_TOL * along:
        line = sorted(range(n), key=lambda k: float(P[k] @ d))
        why = (f"the {n} camera centres lie on one straight line (RMS offset {across:.3g}, "
               f"{100 * across / max(along, 1e-300):.1f}% of their spread {along:.3g} along it)")
        segs = _segments_along([line], P, extend)
        headings = _headings_across(cams, F, d, scene_depth)
        if headings is not None:
            # One photo from each strip of a mapping flight: the strips run along the cameras'
            # heading, across this line; poses along them get as many draws as those across.
            across_strips, facing = headings
            heads_len = sum(2.0 * float(np.linalg.norm(v)) for v in across_strips)  # t from -1 to 1
            w = sum(sg.length(C) for sg in segs) / max(heads_len, 1e-300)
            segs += [Segment(i, i, -1.0, 1.0, direction=v, weight=w) for i, v in enumerate(across_strips)]
            who, rest = ("each camera faces", "") if facing == n else (f"{facing} of the {n} cameras face",
                                                                     " (square to the line for the others)")
            why += (f"; {who} across it (image up within 30 deg of square to it): one photo a strip, poses "
                    f"also along each camera's heading{rest}")
        return Trajectory("strips", why, up, spacing, lines=[line], segments=segs)
    orbit = fit_orbit(cams, up)
    is_orbit, why_orbit = _orbit_evidence(cams, orbit, F, P)
    if is_orbit:
        return Trajectory("orbit", why_orbit, up, spacing, orbit=orbit)
    grid = _parallel_lines(P, spacing) if n >= 4 else None
    if grid is not None:
        lines, worst = grid
        segs = _segments_along(lines, P, extend)
        # Between adjacent lines: each camera and its nearest camera on the next line.
        order = sorted(range(len(lines)), key=lambda k: float(np.mean(P[lines[k]], 0) @ np.array([-d[1], d[0]])))
        for la, lb in zip(order[:-1], order[1:]):
            for a in lines[la]:
                b = min(lines[lb], key=lambda k: float(np.linalg.norm(P[k] - P[a])))
                segs.append(Segment(a, b))
        return Trajectory("strips", f"the {n} camera centres lie on {len(lines)} parallel straight lines "
                          f"(worst offset {worst:.3g}, {100 * worst / spacing:.0f}% of the camera spacing "
                          f"{spacing:.3g})", up, spacing, lines=lines, segments=segs)
    pairs = _neighbour_pairs(P)
    return Trajectory("free", f"neither one straight line ({100 * across / max(along, 1e-300):.0f}% spread "
                      f"across it), parallel lines, nor an orbit ({why_orbit}): poses between the "
                      f"{len(pairs)} pairs of neighbouring cameras", up, spacing,
                      segments=[Segment(a, b) for a, b in pairs])


# -- Sampling -----------------------------------------------------------------
def _jitter(eye: np.ndarray, R: np.ndarray, rng: np.random.Generator, sigma: float, F: np.ndarray,
            look_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Shift ``eye`` (horizontal sigma, vertical sigma/2) and tilt the optical axis of ``R`` (world->camera)
    by a normal angle of ``look_deg`` degrees about a random axis across it."""
    off = rng.normal(size=3) * np.array([sigma, sigma, 0.5 * sigma])
    eye = eye + off @ F
    phi = rng.uniform(0, 2 * np.pi)
    ang = np.radians(look_deg) * rng.normal()
    Rj = axis_angle(np.array([np.cos(phi), np.sin(phi), 0.0]), ang)
    return eye, Rj @ R


def _camera(R: np.ndarray, eye: np.ndarray, like: Camera, name: str) -> Camera:
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return Camera(K=like.K.copy(), w2c=w2c, width=like.width, height=like.height, name=name,
                  depth_range=like.depth_range)


def sample_poses(traj: Trajectory, cams: Sequence[Camera], n: int, seed: int, jitter: float = 0.1,
                 look_deg: float = 2.0) -> list[Camera]:
    """``n`` cameras on ``traj`` (seeded; the first ``k`` of ``n`` are the ``k`` of a smaller draw).

    * orbit: uniform angles on the whole circle (the paper), looking at the orbit's target;
    * otherwise: a segment of ``traj.segments`` at random (weighted by its length), a point on
      it, the rotation slerped between its cameras.

    Every pose is then jittered: position by ``jitter`` x the length of its segment (an orbit: the
    smaller of the camera spacing and the radius, x :func:`.frame.span_factor`; horizontally, half
    that vertically), look direction by ``look_deg`` degrees x the span factor: the view of an orbit
    100 x as far through a lens 100 x as long moves by the same share of the image. Intrinsics and
    image size come from the nearer camera of the segment (an orbit: the first one); names ``pseudo_000``...
    """
    cams = list(cams)
    if n <= 0:
        return []
    rng = np.random.default_rng(seed)
    F = up_frame(traj.up)
    out = []
    span = span_factor(cams)
    look_deg = look_deg * span
    if traj.kind == "orbit" and traj.orbit is not None:
        o = traj.orbit
        sigma = jitter * min(traj.spacing, o.radius) * span
        for i in range(n):
            eye = o.point(rng.uniform(0.0, 2.0 * np.pi))
            R = look_at(eye, o.target, o.normal)[:3, :3]
            eye, R = _jitter(eye, R, rng, sigma, F, look_deg)
            out.append(_camera(R, eye, cams[0], f"pseudo_{i:03d}"))
        return out
    segs = traj.segments or [Segment(0, 0)]
    C = np.stack([c.center for c in cams])
    lens = np.array([max(s.length(C) * s.weight, 1e-12) for s in segs])
    prob = lens / lens.sum()
    for i in range(n):
        s = segs[int(rng.choice(len(segs), p=prob))]
        t = float(rng.uniform(s.t0, s.t1))
        eye = s.point(C, t)
        tc = min(max(t, 0.0), 1.0)
        R = slerp(cams[s.a].R, cams[s.b].R, tc)
        seg_len = float(np.linalg.norm(s.step(C)))
        sigma = jitter * (seg_len if seg_len > 0 else traj.spacing)
        eye, R = _jitter(eye, R, rng, sigma, F, look_deg)
        like = cams[s.a] if tc < 0.5 else cams[s.b]
        out.append(_camera(R, eye, like, f"pseudo_{i:03d}"))
    return out


__all__ = ["TrajectoryKind", "Trajectory", "Segment", "classify", "sample_poses", "LINE_TOL"]
