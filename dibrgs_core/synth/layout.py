"""Scene layout of the generated aerial scenes (NumPy, no bpy): procedural geometry (city,
village, mountain, stadium) as coloured polygon meshes. How the scenes are photographed:
:mod:`.flights`.

World units are metres, the ground is the plane z = 0 and +Z is up *in the generated
scenes only* (the library estimates up from the cameras). Pixels whose ray hits nothing
have depth 0 (the ground plane is large enough that no view sees the sky).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..common.modes import SceneKind, choices

log = logging.getLogger("dibrgs.scenegen")

KINDS = choices(SceneKind)


# ---------------------------------------------------------------------------
# Geometry (numpy; world coordinates, metres, z up)
# ---------------------------------------------------------------------------
@dataclass
class MeshData:
    """Polygons with one RGB colour per vertex (attribute ``col``) and a second one (``col2``)."""

    verts: np.ndarray  # (V,3)
    faces: list        # list of vertex-index lists
    col: np.ndarray    # (V,3)
    col2: np.ndarray   # (V,3)


def merge(parts: list[MeshData]) -> MeshData:
    verts, faces, col, col2, off = [], [], [], [], 0
    for p in parts:
        verts.append(p.verts)
        faces += [[i + off for i in f] for f in p.faces]
        col.append(p.col)
        col2.append(p.col2)
        off += len(p.verts)
    return MeshData(np.concatenate(verts), faces, np.concatenate(col), np.concatenate(col2))


def _boxes(cx, cy, hx, hy, h, ang, col, col2, z0=None) -> MeshData:
    """Closed-top boxes (no bottom face), footprint rotated by ``ang`` about z."""
    n = len(cx)
    z0 = np.zeros(n) if z0 is None else np.asarray(z0)
    sx = np.array([-1, 1, 1, -1])
    sy = np.array([-1, -1, 1, 1])
    ca, sa = np.cos(ang)[:, None], np.sin(ang)[:, None]
    lx, ly = sx[None] * hx[:, None], sy[None] * hy[:, None]
    x = cx[:, None] + ca * lx - sa * ly
    y = cy[:, None] + sa * lx + ca * ly
    bottom = np.stack([x, y, np.broadcast_to(z0[:, None], x.shape)], -1)
    top = np.stack([x, y, (z0 + h)[:, None].repeat(4, 1)], -1)
    verts = np.concatenate([bottom, top], 1).reshape(-1, 3)
    local = [[0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7], [4, 5, 6, 7]]
    faces = [[8 * b + i for i in f] for b in range(n) for f in local]
    return MeshData(verts, faces, np.repeat(col, 8, 0), np.repeat(col2, 8, 0))


def _gable_roofs(cx, cy, hx, hy, h, ang, rise, col) -> MeshData:
    """Pitched roofs on top of boxes, ridge along the local x axis."""
    n = len(cx)
    lx = np.stack([-hx, hx, hx, -hx, -hx, hx], 1)
    ly = np.stack([-hy, -hy, hy, hy, np.zeros(n), np.zeros(n)], 1)
    lz = np.stack([h, h, h, h, h + rise, h + rise], 1)
    ca, sa = np.cos(ang)[:, None], np.sin(ang)[:, None]
    x = cx[:, None] + ca * lx - sa * ly
    y = cy[:, None] + sa * lx + ca * ly
    verts = np.stack([x, y, lz], -1).reshape(-1, 3)
    local = [[0, 1, 5, 4], [2, 3, 4, 5], [3, 0, 4], [1, 2, 5]]
    faces = [[6 * b + i for i in f] for b in range(n) for f in local]
    c = np.repeat(col, 6, 0)
    return MeshData(verts, faces, c, c)


def _ellipsoids(cx, cy, cz, rx, rz, col, seg: int = 8, rings: int = 5) -> MeshData:
    """Low-poly ellipsoids (tree crowns)."""
    n = len(cx)
    th = np.linspace(0, 2 * np.pi, seg, endpoint=False)
    ph = np.linspace(0, np.pi, rings + 2)[1:-1]
    unit = [(0.0, 0.0, 1.0)] + [(np.sin(p) * np.cos(t), np.sin(p) * np.sin(t), np.cos(p)) for p in ph for t in th]
    unit.append((0.0, 0.0, -1.0))
    u = np.array(unit)
    nv = len(u)
    verts = (np.stack([cx, cy, cz], 1)[:, None] + u[None] * np.stack([rx, rx, rz], 1)[:, None]).reshape(-1, 3)
    local = [[0, 1 + (i + 1) % seg, 1 + i] for i in range(seg)]
    for r in range(rings - 1):
        a, b = 1 + r * seg, 1 + (r + 1) * seg
        local += [[a + i, a + (i + 1) % seg, b + (i + 1) % seg, b + i] for i in range(seg)]
    last = nv - 1
    a = 1 + (rings - 1) * seg
    local += [[a + i, last, a + (i + 1) % seg][::-1] for i in range(seg)]
    faces = [[nv * k + i for i in f] for k in range(n) for f in local]
    c = np.repeat(col, nv, 0)
    return MeshData(verts, faces, c, c)


def _grid(xs: np.ndarray, ys: np.ndarray, z: np.ndarray) -> MeshData:
    """Height-field grid mesh; z has shape (len(ys), len(xs))."""
    X, Y = np.meshgrid(xs, ys)
    verts = np.stack([X.ravel(), Y.ravel(), z.ravel()], 1)
    nx, ny = len(xs), len(ys)
    idx = np.arange(nx * ny).reshape(ny, nx)
    q = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    c = np.ones((len(verts), 3)) * 0.5
    return MeshData(verts, q.tolist(), c, c)


def _palette(rng: np.random.Generator, n: int, base: np.ndarray, jitter: float) -> np.ndarray:
    """``n`` colours drawn from the rows of ``base`` with multiplicative jitter."""
    c = base[rng.integers(0, len(base), n)] * rng.uniform(1 - jitter, 1 + jitter, (n, 1))
    return np.clip(c * rng.uniform(0.92, 1.08, (n, 3)), 0.02, 0.95)


FACADES = np.array([[0.62, 0.6, 0.56], [0.7, 0.66, 0.58], [0.55, 0.5, 0.45], [0.75, 0.74, 0.72],
                    [0.6, 0.42, 0.32], [0.45, 0.48, 0.52], [0.78, 0.7, 0.55], [0.4, 0.36, 0.34]])
ROOFS = np.array([[0.35, 0.35, 0.36], [0.5, 0.5, 0.48], [0.25, 0.27, 0.3], [0.6, 0.58, 0.52],
                  [0.3, 0.4, 0.32], [0.55, 0.3, 0.25]])
TILES = np.array([[0.55, 0.22, 0.15], [0.45, 0.2, 0.14], [0.35, 0.3, 0.28], [0.6, 0.35, 0.2]])
GREENS = np.array([[0.12, 0.25, 0.08], [0.18, 0.3, 0.1], [0.1, 0.2, 0.1], [0.22, 0.3, 0.12]])

# City block grid: roads of width ROAD at x (or y) in [k*BLOCK, k*BLOCK + ROAD].
BLOCK, ROAD = 40.0, 10.0


def city_parts(rng: np.random.Generator) -> list[MeshData]:
    cx, cy, hx, hy, h, ang = [], [], [], [], [], []
    trees = []
    for bx in range(-3, 3):
        for by in range(-3, 3):
            x0, y0 = bx * BLOCK + ROAD, by * BLOCK + ROAD
            size = BLOCK - ROAD
            r = rng.random()
            if r < 0.12:  # park: trees only
                m = rng.integers(4, 10)
                trees.append(np.stack([x0 + rng.uniform(3, size - 3, m), y0 + rng.uniform(3, size - 3, m)], 1))
                continue
            split = rng.choice([1, 2, 4], p=[0.35, 0.35, 0.3])
            lots = {1: [(0, 0, 1, 1)], 2: [(0, 0, 0.5, 1), (0.5, 0, 1, 1)] if rng.random() < 0.5 else
                    [(0, 0, 1, 0.5), (0, 0.5, 1, 1)], 4: [(0, 0, .5, .5), (.5, 0, 1, .5), (0, .5, .5, 1), (.5, .5, 1, 1)]}[split]
            central = max(abs(bx + 0.5), abs(by + 0.5)) < 1.6  # taller towers near the centre
            for (u0, v0, u1, v1) in lots:
                w, d = (u1 - u0) * size, (v1 - v0) * size
                fw, fd = rng.uniform(0.55, 0.85, 2)
                cx.append(x0 + (u0 + u1) / 2 * size + rng.uniform(-1, 1) * (1 - fw) * w / 2)
                cy.append(y0 + (v0 + v1) / 2 * size + rng.uniform(-1, 1) * (1 - fd) * d / 2)
                hx.append(fw * w / 2)
                hy.append(fd * d / 2)
                h.append(float(np.clip(rng.lognormal(np.log(28 if central else 14), 0.5), 6, 90)))
                ang.append(rng.normal(0, 0.05))
    n = len(cx)
    cx, cy, hx, hy, h, ang = map(np.asarray, (cx, cy, hx, hy, h, ang))
    parts = [_boxes(cx, cy, hx, hy, h, ang, _palette(rng, n, FACADES, 0.15), _palette(rng, n, ROOFS, 0.2))]
    # Rooftop structures (lift shafts, AC units) on some buildings.
    k = rng.random(n) < 0.6
    m = int(k.sum())
    parts.append(_boxes(cx[k] + rng.uniform(-.3, .3, m) * hx[k], cy[k] + rng.uniform(-.3, .3, m) * hy[k],
                        rng.uniform(1.5, 4, m), rng.uniform(1.5, 4, m), rng.uniform(1.5, 4, m), ang[k],
                        _palette(rng, m, ROOFS, 0.2), _palette(rng, m, ROOFS, 0.2), z0=h[k]))
    if trees:
        t = np.concatenate(trees)
        m = len(t)
        r = rng.uniform(2, 4, m)
        parts.append(_ellipsoids(t[:, 0], t[:, 1], r * 1.1, r, r * 1.1, _palette(rng, m, GREENS, 0.2)))
    return parts


def village_parts(rng: np.random.Generator) -> list[MeshData]:
    n = 70
    pts = []
    while len(pts) < n:  # Poisson-disc-like: reject houses closer than 16 m
        p = rng.uniform(-110, 110, 2)
        if all(np.hypot(*(p - q)) > 16 for q in pts):
            pts.append(p)
    p = np.array(pts)
    hx, hy = rng.uniform(4, 8, n), rng.uniform(3, 5, n)
    h = rng.uniform(3.5, 7.5, n)
    ang = rng.uniform(0, np.pi, n)
    parts = [_boxes(p[:, 0], p[:, 1], hx, hy, h, ang, _palette(rng, n, FACADES, 0.15), _palette(rng, n, TILES, 0.2)),
             _gable_roofs(p[:, 0], p[:, 1], hx * 1.08, hy * 1.15, h, ang, rng.uniform(2, 4, n),
                          _palette(rng, n, TILES, 0.25))]
    m = 260
    t = rng.uniform(-130, 130, (m, 2))
    far = np.min(np.hypot(t[:, None, 0] - p[None, :, 0], t[:, None, 1] - p[None, :, 1]), 1) > 10
    t = t[far]
    m = len(t)
    r = rng.uniform(2.5, 5.5, m)
    parts.append(_ellipsoids(t[:, 0], t[:, 1], r * 1.2, r, r * 1.2, _palette(rng, m, GREENS, 0.25)))
    return parts


def _terrain_height(rng: np.random.Generator, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Sum of random ridged sinusoid octaves, tapered to 0 at radius ~300 m."""
    z = np.zeros_like(X)
    amp, freq = 60.0, 1 / 120.0
    for _ in range(6):
        for _ in range(3):
            a = rng.uniform(0, np.pi)
            ph = rng.uniform(0, 2 * np.pi)
            z += amp / 3 * (1 - np.abs(np.sin(2 * np.pi * freq * (X * np.cos(a) + Y * np.sin(a)) + ph)))
        amp *= 0.45
        freq *= 2.1
    peak = rng.uniform(-40, 40, 2)
    z += 90 * np.exp(-((X - peak[0]) ** 2 + (Y - peak[1]) ** 2) / (2 * 70.0 ** 2))
    r = np.hypot(X, Y)
    taper = np.clip((330 - r) / 120, 0, 1)
    return (z - z.min()) * taper ** 2


def mountain_parts(rng: np.random.Generator, res: int) -> list[MeshData]:
    n = int(np.clip(res // 2, 48, 200))  # grid fine enough for the image resolution
    xs = np.linspace(-330, 330, n)
    X, Y = np.meshgrid(xs, xs)
    return [_grid(xs, xs, _terrain_height(rng, X, Y))]


def stadium_parts(rng: np.random.Generator) -> list[MeshData]:
    a, b = 55.0, 38.0  # inner ellipse semi-axes (track edge)
    seg = 96
    steps = 14
    top = rng.uniform(22, 30)
    s_out = 1.75
    # Stepped profile (scale, z): riser then tread, up to the rim, then the outer wall down.
    prof = [(1.0, 0.0)]
    for i in range(steps):
        s0 = 1.0 + (s_out - 1.0) * i / steps
        s1 = 1.0 + (s_out - 1.0) * (i + 1) / steps
        z = 2.0 + (top - 2.0) * (i + 1) / steps
        prof += [(s0, z), (s1, z)]
    prof += [(s_out + 0.02, top + 1.5), (s_out + 0.04, 0.0)]
    sector = rng.permutation(np.array([[0.7, 0.1, 0.1], [0.1, 0.2, 0.6], [0.85, 0.75, 0.15],
                                       [0.8, 0.8, 0.8], [0.15, 0.45, 0.2], [0.5, 0.15, 0.45]]))
    verts, faces, col = [], [], []
    th = np.linspace(0, 2 * np.pi, seg + 1)
    for j in range(seg):
        for k in range(len(prof) - 1):
            (s0, z0), (s1, z1) = prof[k], prof[k + 1]
            q = [(s0, z0, th[j]), (s0, z0, th[j + 1]), (s1, z1, th[j + 1]), (s1, z1, th[j])]
            base = len(verts)
            verts += [(a * s * np.cos(t), b * s * np.sin(t), z) for s, z, t in q]
            faces.append([base, base + 3, base + 2, base + 1])
            c = sector[(j // 8) % len(sector)] if k < len(prof) - 3 else np.array([0.75, 0.74, 0.7])
            c = c * (0.8 if (k // 2) % 2 else 1.0) * rng.uniform(0.9, 1.1)
            col += [c] * 4
    col = np.clip(np.array(col), 0, 1)
    parts = [MeshData(np.array(verts), faces, col, col)]
    # Field and running track: elliptical discs slightly above the ground.
    ring = lambda s, z: [(a * s * np.cos(t), b * s * np.sin(t), z) for t in th[:-1]]  # noqa: E731
    for s, z, c in ((1.0, 0.05, [0.55, 0.2, 0.15]), (0.86, 0.1, [0.15, 0.42, 0.12])):
        v = np.array([(0.0, 0.0, z)] + ring(s, z))
        f = [[0, 1 + (i + 1) % seg, 1 + i][::-1] for i in range(seg)]
        cc = np.tile(c, (len(v), 1)).astype(float)
        parts.append(MeshData(v, f, cc, cc))
    # Surrounding low buildings and parking.
    m = 30
    ang = rng.uniform(0, 2 * np.pi, m)
    rad = rng.uniform(1.25, 1.6, m) * 100
    parts.append(_boxes(rad * np.cos(ang), rad * np.sin(ang), rng.uniform(6, 14, m), rng.uniform(6, 14, m),
                        rng.uniform(5, 20, m), ang, _palette(rng, m, FACADES, 0.15), _palette(rng, m, ROOFS, 0.2)))
    return parts




