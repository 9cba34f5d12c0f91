"""Procedural aerial scenes rendered headless with Blender (bpy, Cycles on CPU).

LEVIR-NVS images cannot be downloaded here, so the project renders its own
scenes in the same layout, with exact cameras and ground-truth depth::

    OUT/Images/NNN.png     8-bit sRGB views 000-020
    OUT/Cams/NNN.txt       LEVIR cameras (w2c, K, DEPTH_MIN DEPTH_MAX)
    OUT/Depths/NNN.tiff    float32 z-depth (distance along the camera axis, metres)
    OUT/Depths/NNN.exr     the same depth as a 32-bit EXR (channel "Z")
    OUT/Track/NNN.txt      60 render-path cameras on the orbit
    OUT/scene.json         generator settings (kind, seed, resolution, samples, orbit)

World units are metres, the ground is the plane z = 0 and +Z is up *in the
generated scenes only* (the library estimates up from the cameras). View 000
looks down near nadir; views 001-020 sit on a horizontal circular orbit looking
at the scene centre: 15 degrees off nadir by default (orbit ``levir``), or 35.5
degrees (orbit ``wide``, a stiffer case with heavy occlusion between views 126
degrees apart). Pixels whose
ray hits nothing have depth 0 (the ground plane is large enough that orbit
views never see the sky).

Everything is seeded: the geometry comes from ``numpy.random.default_rng(seed)``
and Cycles uses a fixed sampling seed, so the same seed gives the same images.
"""
from __future__ import annotations

import logging
import math
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera.pinhole import Camera, look_at
from ..camera.blender import to_blender
from ..common.fileio import write_json

log = logging.getLogger("dibrgs.scenegen")

KINDS = ("city", "mountain", "village", "stadium")
N_ORBIT = 20
N_TRACK = 60


@dataclass(frozen=True)
class OrbitSpec:
    """Acquisition geometry of a generated scene (metres, degrees)."""

    radius: float = 150.0       # orbit radius around the scene centre (these defaults: the "wide" orbit)
    height: float = 210.0       # orbit height above the ground (off-nadir ~35.5 deg)
    nadir_height: float = 300.0  # height of the near-nadir view 000
    nadir_offset_deg: float = 4.0  # view 000's angle off nadir
    lens_mm: float = 35.0       # on a 36 mm sensor: ~54 deg horizontal field of view
    sensor_mm: float = 36.0

    @property
    def off_nadir_deg(self) -> float:
        return math.degrees(math.atan2(self.radius, self.height))


# LEVIR-NVS is built for "limited view-perspective variations" (its authors' words) and its
# reference method renders every view from one multiplane image in view 000's frustum, which
# only holds for views a few tens of degrees around nadir; ``levir`` keeps the orbit 15 degrees
# off nadir. ``wide`` (35.5 degrees) is the stiff case: views 001/008/015 are 126 degrees apart
# in heading and see few of the same street-level pixels between tall buildings.
ORBITS: dict[str, OrbitSpec] = {
    "levir": OrbitSpec(radius=210.0 * math.tan(math.radians(15.0))),
    "wide": OrbitSpec(),
}
DEFAULT_ORBIT = "levir"


# ---------------------------------------------------------------------------
# Cameras
# ---------------------------------------------------------------------------
def scene_cameras(resolution: int, phase: float, spec: OrbitSpec = ORBITS[DEFAULT_ORBIT]) -> tuple[list[Camera], list[Camera]]:
    """Views 000-020 and the 60 Track cameras of a generated scene.

    ``phase`` (radians) rotates the orbit start. Returns (views, track) with
    square images of ``resolution`` pixels and a centred principal point.
    """
    W = H = int(resolution)
    f = spec.lens_mm / spec.sensor_mm * W
    K = np.array([[f, 0.0, W / 2.0], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])
    target = np.zeros(3)
    up = np.array([0.0, 0.0, 1.0])
    off = spec.nadir_height * math.tan(math.radians(spec.nadir_offset_deg))
    eye0 = np.array([off * math.cos(phase + math.pi), off * math.sin(phase + math.pi), spec.nadir_height])
    # Near nadir the image "up" is the scene's +Y (north).
    views = [Camera(K=K, w2c=look_at(eye0, target, [0.0, 1.0, 0.0]), width=W, height=H, name="000")]

    def ring(thetas: np.ndarray, names: list[str]) -> list[Camera]:
        out = []
        for th, name in zip(thetas, names):
            eye = np.array([spec.radius * math.cos(th), spec.radius * math.sin(th), spec.height])
            out.append(Camera(K=K, w2c=look_at(eye, target, up), width=W, height=H, name=name))
        return out

    th = phase + 2 * np.pi * np.arange(N_ORBIT) / N_ORBIT
    views += ring(th, [f"{i + 1:03d}" for i in range(N_ORBIT)])
    # The track interleaves with the orbit views (half a step of 60 ahead).
    tt = phase + 2 * np.pi * (np.arange(N_TRACK) + 0.5) / N_TRACK
    track = ring(tt, [f"{i:03d}" for i in range(N_TRACK)])
    return views, track


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


def _merge(parts: list[MeshData]) -> MeshData:
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


def _city_parts(rng: np.random.Generator) -> list[MeshData]:
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


def _village_parts(rng: np.random.Generator) -> list[MeshData]:
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


def _mountain_parts(rng: np.random.Generator, res: int) -> list[MeshData]:
    n = int(np.clip(res // 2, 48, 200))  # grid fine enough for the image resolution
    xs = np.linspace(-330, 330, n)
    X, Y = np.meshgrid(xs, xs)
    return [_grid(xs, xs, _terrain_height(rng, X, Y))]


def _stadium_parts(rng: np.random.Generator) -> list[MeshData]:
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


# ---------------------------------------------------------------------------
# Blender scene
# ---------------------------------------------------------------------------
def _add_mesh(bpy, name: str, md: MeshData, mat) -> None:
    me = bpy.data.meshes.new(name)
    me.from_pydata(md.verts.tolist(), [], md.faces)
    me.update()
    for an, arr in (("col", md.col), ("col2", md.col2)):
        at = me.color_attributes.new(an, "FLOAT_COLOR", "POINT")
        rgba = np.concatenate([arr, np.ones((len(arr), 1))], 1).astype(np.float32)
        at.data.foreach_set("color", rgba.ravel())
    me.materials.append(mat)
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)


def _enable_nodes(idblock) -> None:
    """Give a material/world its node tree (Blender 5 always has one; use_nodes is deprecated)."""
    if idblock.node_tree is None:
        idblock.use_nodes = True


class _Nodes:
    """Small helper to build shader node graphs by name."""

    def __init__(self, mat):
        _enable_nodes(mat)
        self.nt = mat.node_tree
        self.nt.nodes.clear()

    def n(self, kind: str, **props):
        node = self.nt.nodes.new(kind)
        for k, v in props.items():
            if k in node.inputs:
                node.inputs[k].default_value = v
            else:
                setattr(node, k, v)
        return node

    def link(self, a, b) -> None:
        self.nt.links.new(a, b)

    def math(self, op: str, a, b=None, **kw):
        m = self.n("ShaderNodeMath", operation=op, **kw)
        for i, x in enumerate((a, b)):
            if x is None:
                continue
            if isinstance(x, (int, float)):
                m.inputs[i].default_value = x
            else:
                self.link(x, m.inputs[i])
        return m.outputs[0]

    def mix(self, fac, c1, c2, blend: str = "MIX"):
        m = self.n("ShaderNodeMix", data_type="RGBA", blend_type=blend)
        for sock, x in ((m.inputs[0], fac), (m.inputs[6], c1), (m.inputs[7], c2)):
            if isinstance(x, (int, float)):
                sock.default_value = x
            elif isinstance(x, (tuple, list)):
                sock.default_value = (*x[:3], 1.0)
            else:
                self.link(x, sock)
        return m.outputs[2]

    def mul(self, color, factor):
        """``color * factor`` for a scalar or colour factor (no clamping)."""
        return self.mix(1.0, color, factor, "MULTIPLY")

    def output(self, color) -> None:
        bsdf = self.n("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Roughness"].default_value = 0.5
        self.link(color, bsdf.inputs["Color"])
        out = self.n("ShaderNodeOutputMaterial")
        self.link(bsdf.outputs[0], out.inputs["Surface"])


def _coords(g: _Nodes, offset: np.ndarray):
    """Object (= world, identity transforms) coordinates shifted by a seed offset."""
    tc = g.n("ShaderNodeTexCoord")
    mp = g.n("ShaderNodeMapping")
    mp.inputs["Location"].default_value = tuple(offset)
    g.link(tc.outputs["Object"], mp.inputs["Vector"])
    return tc.outputs["Object"], mp.outputs[0]


def _detail(g: _Nodes, vec, scale: float, lo: float, hi: float, roughness: float = 0.6):
    """Multi-octave noise mapped to [lo, hi]: fine texture for feature matching."""
    nz = g.n("ShaderNodeTexNoise", noise_dimensions="3D")
    nz.inputs["Scale"].default_value = scale
    nz.inputs["Detail"].default_value = 5.0  # octaves: finer ones cost render time for little texture
    nz.inputs["Roughness"].default_value = roughness
    g.link(vec, nz.inputs["Vector"])
    return _remap(g, nz.outputs["Fac"], 0.2, 0.8, lo, hi)


def _remap(g: _Nodes, x, a: float, b: float, lo: float, hi: float):
    m = g.n("ShaderNodeMapRange", clamp=True)
    m.inputs["From Min"].default_value = a
    m.inputs["From Max"].default_value = b
    m.inputs["To Min"].default_value = lo
    m.inputs["To Max"].default_value = hi
    g.link(x, m.inputs["Value"])
    return m.outputs["Result"]


def _attr(g: _Nodes, name: str):
    return g.n("ShaderNodeAttribute", attribute_name=name).outputs["Color"]


def _mat_objects(bpy, offset: np.ndarray, windows: bool):
    """Vertex-coloured objects: facades with window grids (walls) and noisy roofs."""
    mat = bpy.data.materials.new("objects_win" if windows else "objects")
    g = _Nodes(mat)
    obj, vec = _coords(g, offset)
    wall, roof = _attr(g, "col"), _attr(g, "col2")
    col_wall = g.mul(wall, _detail(g, vec, 0.35, 0.8, 1.15))
    if windows:
        # Window grid on vertical walls: bricks in (x + y, z), one row per storey.
        sep = g.n("ShaderNodeSeparateXYZ")
        g.link(obj, sep.inputs[0])
        comb = g.n("ShaderNodeCombineXYZ")
        g.link(g.math("ADD", sep.outputs[0], sep.outputs[1]), comb.inputs[0])
        g.link(sep.outputs[2], comb.inputs[1])
        br = g.n("ShaderNodeTexBrick", offset=0.0, squash=1.0)
        for k, v in (("Scale", 1.0), ("Mortar Size", 0.9), ("Brick Width", 3.0), ("Row Height", 3.3),
                     ("Mortar Smooth", 0.0)):
            br.inputs[k].default_value = v
        g.link(comb.outputs[0], br.inputs["Vector"])
        glass = g.mul((0.08, 0.1, 0.14), _detail(g, vec, 2.0, 0.5, 1.6))
        col_wall = g.mix(br.outputs["Fac"], glass, col_wall)
    vor = g.n("ShaderNodeTexVoronoi")
    vor.inputs["Scale"].default_value = 0.6
    g.link(vec, vor.inputs["Vector"])
    speck = _remap(g, vor.outputs["Distance"], 0.0, 0.5, 0.7, 1.1)
    col_roof = g.mul(roof, speck)
    col_roof = g.mul(col_roof, _detail(g, vec, 0.8, 0.8, 1.1))
    geo = g.n("ShaderNodeNewGeometry")
    sep_n = g.n("ShaderNodeSeparateXYZ")
    g.link(geo.outputs["Normal"], sep_n.inputs[0])
    is_roof = g.math("GREATER_THAN", sep_n.outputs[2], 0.5)
    g.output(g.mix(is_roof, col_wall, col_roof))
    return mat


def _cell_colour(g: _Nodes, obj, px: float, py: float, palette: list, offset: np.ndarray):
    """A colour per grid cell of size (px, py) chosen from ``palette`` by a hashed cell id."""
    sep = g.n("ShaderNodeSeparateXYZ")
    g.link(obj, sep.inputs[0])
    comb = g.n("ShaderNodeCombineXYZ")
    g.link(g.math("FLOOR", g.math("DIVIDE", sep.outputs[0], px)), comb.inputs[0])
    g.link(g.math("FLOOR", g.math("DIVIDE", sep.outputs[1], py)), comb.inputs[1])
    comb.inputs[2].default_value = float(offset[2])
    wn = g.n("ShaderNodeTexWhiteNoise", noise_dimensions="3D")
    g.link(comb.outputs[0], wn.inputs["Vector"])
    ramp = g.n("ShaderNodeValToRGB")
    cr = ramp.color_ramp
    cr.interpolation = "CONSTANT"
    while len(cr.elements) < len(palette):
        cr.elements.new(0.5)
    for i, c in enumerate(palette):
        cr.elements[i].position = i / len(palette)
        cr.elements[i].color = (*c, 1.0)
    g.link(wn.outputs["Value"], ramp.inputs["Fac"])
    return ramp.outputs["Color"], sep


def _mat_ground(bpy, offset: np.ndarray, kind: str):
    """Ground: city blocks with roads, or village fields with dirt tracks."""
    mat = bpy.data.materials.new("ground")
    g = _Nodes(mat)
    obj, vec = _coords(g, offset)
    if kind == "village":
        pal = [(0.2, 0.32, 0.1), (0.35, 0.4, 0.15), (0.55, 0.5, 0.25), (0.4, 0.3, 0.18), (0.25, 0.38, 0.12),
               (0.5, 0.45, 0.3)]
        cell, sep = _cell_colour(g, obj, 45.0, 30.0, pal, offset)
        per, road_w, road_c = (45.0, 30.0), 2.5, (0.45, 0.38, 0.28)
    else:
        pal = [(0.3, 0.3, 0.3), (0.4, 0.38, 0.35), (0.2, 0.3, 0.12), (0.35, 0.33, 0.3), (0.25, 0.25, 0.27),
               (0.45, 0.42, 0.38)]
        cell, sep = _cell_colour(g, obj, BLOCK, BLOCK, pal, offset)
        per, road_w, road_c = (BLOCK, BLOCK), ROAD, (0.1, 0.1, 0.11)
    road = None
    for ax, p in zip((0, 1), per):
        m = g.math("LESS_THAN", g.math("FRACT", g.math("DIVIDE", sep.outputs[ax], p)), road_w / p)
        road = m if road is None else g.math("MAXIMUM", road, m)
    vor = g.n("ShaderNodeTexVoronoi")
    vor.inputs["Scale"].default_value = 0.35
    g.link(vec, vor.inputs["Vector"])
    lots = g.mul(cell, _remap(g, vor.outputs["Distance"], 0.0, 0.6, 0.65, 1.15))
    lots = g.mul(lots, _detail(g, vec, 0.08, 0.7, 1.2))
    roads = g.mul(road_c, _detail(g, vec, 0.5, 0.7, 1.3))
    g.output(g.mix(road, lots, roads))
    return mat


def _mat_terrain(bpy, offset: np.ndarray):
    """Terrain coloured by height and slope, with multi-scale noise."""
    mat = bpy.data.materials.new("terrain")
    g = _Nodes(mat)
    obj, vec = _coords(g, offset)
    sep = g.n("ShaderNodeSeparateXYZ")
    g.link(obj, sep.inputs[0])
    hnoise = g.math("ADD", sep.outputs[2], g.math("MULTIPLY", _detail(g, vec, 0.03, -1, 1), 15.0))
    ramp = g.n("ShaderNodeValToRGB")
    cr = ramp.color_ramp
    stops = [(0.0, (0.2, 0.3, 0.1)), (0.3, (0.12, 0.22, 0.08)), (0.55, (0.35, 0.3, 0.2)),
             (0.8, (0.45, 0.43, 0.4)), (0.95, (0.85, 0.85, 0.88))]
    while len(cr.elements) < len(stops):
        cr.elements.new(0.5)
    for e, (p, c) in zip(cr.elements, stops):
        e.position, e.color = p, (*c, 1.0)
    g.link(g.math("DIVIDE", hnoise, 160.0), ramp.inputs["Fac"])
    geo = g.n("ShaderNodeNewGeometry")
    sn = g.n("ShaderNodeSeparateXYZ")
    g.link(geo.outputs["Normal"], sn.inputs[0])
    rock = _remap(g, sn.outputs[2], 0.7, 0.85, 1.0, 0.0)
    col = g.mix(rock, ramp.outputs["Color"], (0.4, 0.37, 0.33))
    vor = g.n("ShaderNodeTexVoronoi")
    vor.inputs["Scale"].default_value = 0.3
    g.link(vec, vor.inputs["Vector"])
    col = g.mul(col, _remap(g, vor.outputs["Distance"], 0.0, 0.6, 0.6, 1.15))
    g.output(g.mul(col, _detail(g, vec, 0.15, 0.7, 1.25)))
    return mat


def _build_scene(bpy, kind: str, resolution: int, rng: np.random.Generator, samples: int) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    offset = rng.uniform(-1000, 1000, 3)
    if kind == "mountain":
        for md in _mountain_parts(rng, resolution):
            _add_mesh(bpy, "terrain", md, _mat_terrain(bpy, offset))
    else:
        parts = {"city": _city_parts, "village": _village_parts, "stadium": _stadium_parts}[kind](rng)
        _add_mesh(bpy, "objects", _merge(parts), _mat_objects(bpy, offset, windows=kind == "city"))
    if kind != "mountain":
        # Flat ground, large enough to fill every orbit view (no sky visible).
        g = np.array([[-1500, -1500, 0], [1500, -1500, 0], [1500, 1500, 0], [-1500, 1500, 0.0]])
        c = np.full((4, 3), 0.5)
        _add_mesh(bpy, "ground", MeshData(g, [[0, 1, 2, 3]], c, c), _mat_ground(bpy, offset, kind))
    else:
        g = np.array([[-1500, -1500, 0], [1500, -1500, 0], [1500, 1500, 0], [-1500, 1500, 0.0]])
        c = np.full((4, 3), 0.5)
        _add_mesh(bpy, "plain", MeshData(g, [[0, 1, 2, 3]], c, c), _mat_terrain(bpy, offset))

    # Sun (fixed per seed) and a uniform sky.
    sun = bpy.data.lights.new("sun", "SUN")
    sun.energy = 3.5
    sun.angle = math.radians(1.0)
    sun_ob = bpy.data.objects.new("sun", sun)
    az, el = rng.uniform(0, 2 * np.pi), math.radians(rng.uniform(45, 65))
    sun_ob.rotation_euler = (math.pi / 2 - el, 0.0, az)
    sc.collection.objects.link(sun_ob)
    world = bpy.data.worlds.new("sky")
    _enable_nodes(world)
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (0.45, 0.6, 0.85, 1.0)
    bg.inputs["Strength"].default_value = 0.7
    sc.world = world

    r = sc.render
    r.engine = "CYCLES"
    r.resolution_x = r.resolution_y = resolution
    r.resolution_percentage = 100
    r.use_persistent_data = True  # keep the BVH between views
    if hasattr(r.image_settings, "media_type"):  # Blender >= 5.0 picks multilayer via media_type
        r.image_settings.media_type = "MULTI_LAYER_IMAGE"
    r.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    r.image_settings.color_depth = "32"
    r.image_settings.exr_codec = "ZIP"
    cy = sc.cycles
    cy.device = "CPU"
    cy.samples = samples
    cy.use_adaptive_sampling = False
    cy.use_denoising = False
    cy.seed = 0
    cy.max_bounces = 2
    cy.diffuse_bounces = 1
    cy.glossy_bounces = cy.transmission_bounces = cy.volume_bounces = cy.transparent_max_bounces = 0
    cy.caustics_reflective = cy.caustics_refractive = False
    sc.view_settings.view_transform = "Standard"
    cam = bpy.data.cameras.new("cam")
    cam_ob = bpy.data.objects.new("cam", cam)
    sc.collection.objects.link(cam_ob)
    sc.camera = cam_ob


def _set_camera(bpy, cam: Camera) -> None:
    p = to_blender(cam)
    sc = bpy.context.scene
    ob = sc.camera
    d = ob.data
    d.lens, d.sensor_width, d.sensor_height, d.sensor_fit = p.lens, p.sensor_width, p.sensor_height, p.sensor_fit
    d.shift_x, d.shift_y = p.shift_x, p.shift_y
    d.clip_start, d.clip_end = 1.0, 10000.0
    sc.render.pixel_aspect_x, sc.render.pixel_aspect_y = p.pixel_aspect_x, p.pixel_aspect_y
    from mathutils import Matrix

    ob.matrix_world = Matrix([list(map(float, row)) for row in p.matrix_world])  # rows, not columns


def _render_rgb(bpy, path: Path) -> np.ndarray:
    """Render the current camera; linear RGB float32 (H, W, 3) from Blender's multilayer EXR."""
    import OpenEXR

    sc = bpy.context.scene
    bpy.ops.render.render(write_still=False)
    # save_render writes with the scene's (multilayer EXR) settings, without write_still's log line.
    bpy.data.images["Render Result"].save_render(filepath=str(path), scene=sc)
    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        key = next(k for k in ch if k.endswith("Combined.R"))[:-1]
        return np.stack([ch[key + c].pixels for c in "RGB"], -1).astype(np.float32)


def _depth_mode(bpy) -> None:
    """Switch to rendering z-depth as emission: 1 sample through each pixel centre.

    Every surface emits its camera-space z (Camera Data "View Z Depth") and the
    world is black, so a pixel holds the exact z-depth at its centre and 0 where
    the ray hits nothing. (Blender 5.0's bpy does not write the Depth pass into
    the multilayer EXR, and that pass would be jittered by the pixel filter.)
    """
    sc = bpy.context.scene
    mat = bpy.data.materials.new("zdepth")
    g = _Nodes(mat)
    cd = g.n("ShaderNodeCameraData")
    em = g.n("ShaderNodeEmission")
    em.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    g.link(cd.outputs["View Z Depth"], em.inputs["Strength"])
    out = g.n("ShaderNodeOutputMaterial")
    g.link(em.outputs[0], out.inputs["Surface"])
    sc.view_layers[0].material_override = mat
    black = bpy.data.worlds.new("black")
    _enable_nodes(black)
    black.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    sc.world = black
    sc.cycles.samples = 1
    sc.cycles.filter_width = 0.01  # Cycles' minimum: the sample sits at the pixel centre
    sc.cycles.max_bounces = 0


def linear_to_srgb8(rgb: np.ndarray) -> np.ndarray:
    """Scene-linear RGB -> 8-bit sRGB (the piecewise sRGB transfer function, no dither)."""
    x = np.clip(rgb, 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(s * 255.0).astype(np.uint8)


def default_samples(resolution: int) -> int:
    """Cycles samples per pixel: more for tiny test images, where noise is costly to matching."""
    return 32 if resolution <= 128 else 12


def make_scene(kind: str, resolution: int, seed: int, out: str | Path, samples: int | None = None,
               orbit: str = DEFAULT_ORBIT) -> Path:
    """Render a procedural aerial scene into ``out`` in LEVIR-NVS layout (see module docstring).

    Args:
        kind: ``city``, ``mountain``, ``village`` or ``stadium``.
        resolution: image width = height in pixels.
        seed: scene seed; the same seed gives the same scene and images.
        out: output folder (created).
        samples: Cycles samples per pixel (default :func:`default_samples`).
        orbit: acquisition geometry, a key of :data:`ORBITS` (``levir`` or ``wide``).

    Returns the output folder. Must run in a background Blender/bpy process: it
    resets the current Blender file.
    """
    import bpy

    from ..data.levir import write_cams_file
    from ..data.images import write_depth_exr, write_depth_tiff, write_png

    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if resolution < 8:
        raise ValueError(f"resolution must be >= 8, got {resolution}")
    if orbit not in ORBITS:
        raise ValueError(f"orbit must be one of {sorted(ORBITS)}, got {orbit!r}")
    spec = ORBITS[orbit]
    if not bpy.app.background:
        raise RuntimeError("make_scene resets the Blender file; run it in a background process")
    samples = default_samples(resolution) if samples is None else int(samples)
    out = Path(out)
    t0 = time.time()
    rng = np.random.default_rng(seed)
    phase = float(rng.uniform(0, 2 * np.pi))
    views, track = scene_cameras(resolution, phase, spec)
    _build_scene(bpy, kind, resolution, rng, samples)
    bpy.context.scene.render.threads_mode = "AUTO"
    log.info("built %s scene (seed %d) in %.1fs; rendering %d views at %dx%d, %d spp", kind, seed,
             time.time() - t0, len(views), resolution, resolution, samples)
    from tqdm import tqdm

    dmin_all, dmax_all = np.inf, 0.0
    with tempfile.TemporaryDirectory(prefix="dibrgs_scenegen_") as tmp:
        for cam in tqdm(views, desc=f"render {kind} {resolution}px", unit="view"):
            _set_camera(bpy, cam)
            rgb = _render_rgb(bpy, Path(tmp) / f"{cam.name}.exr")
            write_png(out / "Images" / f"{cam.name}.png", linear_to_srgb8(rgb))
        _depth_mode(bpy)
        for cam in tqdm(views, desc="render depth", unit="view"):
            _set_camera(bpy, cam)
            depth = _render_rgb(bpy, Path(tmp) / f"{cam.name}_z.exr")[..., 0]
            depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
            valid = depth[depth > 0]
            dmin, dmax = (float(valid.min()), float(valid.max())) if valid.size else (1.0, 1000.0)
            dmin_all, dmax_all = min(dmin_all, dmin), max(dmax_all, dmax)
            cam.depth_range = (0.95 * dmin, 1.05 * dmax)
            write_depth_tiff(out / "Depths" / f"{cam.name}.tiff", depth)
            write_depth_exr(out / "Depths" / f"{cam.name}.exr", depth)
            write_cams_file(out / "Cams" / f"{cam.name}.txt", cam)
    for cam in track:
        cam.depth_range = (0.95 * dmin_all, 1.05 * dmax_all)
        write_cams_file(out / "Track" / f"{cam.name}.txt", cam)
    write_json(out / "scene.json", {"generator": "dibrgs_core.synth.writer", "kind": kind, "seed": seed,
                                    "resolution": resolution, "samples": samples, "orbit_phase_rad": phase,
                                    "orbit_name": orbit, "orbit": spec.__dict__, "up": [0.0, 0.0, 1.0],
                                    "depth": "z-depth along the camera axis, metres; 0 = no surface"})
    log.info("wrote %s in %.1fs", out, time.time() - t0)
    return out
