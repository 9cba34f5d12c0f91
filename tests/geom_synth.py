"""Small synthetic aerial scenes for the geometry tests, rendered by numpy ray casting.

A textured heightfield (ground plus box buildings) is ray-marched from an
orbit of cameras, giving exact z-depth maps. World units mimic LEVIR-NVS
(cameras ~120 units from the scene). ``up`` lets a test rotate the whole
world so that the scene's up axis is not +Z; ``offset`` translates it (for
georeferenced coordinates).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.data.scene import Scene, View


def _value_noise(rng: np.random.Generator, x: np.ndarray, y: np.ndarray, scales=(40.0, 12.0, 4.0, 1.5)) -> np.ndarray:
    """Smooth multi-octave colour noise at world (x, y): (N, 3) in [0, 1]."""
    out = np.zeros(x.shape + (3,))
    for k, s in enumerate(scales):
        n = 64
        grid = rng.random((n, n, 3))
        u = (x / s) % (n - 1)
        v = (y / s) % (n - 1)
        i0, j0 = np.floor(u).astype(int), np.floor(v).astype(int)
        fu, fv = (u - i0)[..., None], (v - j0)[..., None]
        g = (grid[j0, i0] * (1 - fu) * (1 - fv) + grid[j0, i0 + 1] * fu * (1 - fv)
             + grid[j0 + 1, i0] * (1 - fu) * fv + grid[j0 + 1, i0 + 1] * fu * fv)
        out += g * (1.0 - 0.12 * k)
    out -= out.min()
    return out / max(out.max(), 1e-9)


@dataclass
class HeightField:
    """Ground at height 0 with axis-aligned box buildings (x0, x1, y0, y1, h)."""

    boxes: np.ndarray
    seed: int = 0

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        h = np.zeros_like(x)
        for x0, x1, y0, y1, bh in self.boxes:
            inside = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
            h = np.where(inside, np.maximum(h, bh), h)
        return h

    def color(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        rng = np.random.default_rng(self.seed)
        c = _value_noise(rng, x + 0.37 * z, y - 0.21 * z)
        roof = (z > 0.5)[..., None]
        return np.where(roof, 0.3 + 0.7 * c[..., ::-1], 0.1 + 0.8 * c)


def city_heightfield(seed: int = 0, n_boxes: int = 12, extent: float = 60.0) -> HeightField:
    rng = np.random.default_rng(seed)
    boxes = []
    for _ in range(n_boxes):
        cx, cy = rng.uniform(-extent * 0.7, extent * 0.7, 2)
        w, d = rng.uniform(6, 16, 2)
        boxes.append((cx - w / 2, cx + w / 2, cy - d / 2, cy + d / 2, rng.uniform(5, 25)))
    return HeightField(np.array(boxes), seed)


_RENDERED: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}


def render(hf: HeightField, cam_local: Camera, ss: int = 2, step: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Ray-march ``hf`` (in the local z-up frame). Returns (image HxWx3 float32, z-depth HxW float32).

    Renders are kept for the test session (copies are returned): the same local cameras recur
    across tests and across their world offsets and up axes, and the march costs seconds."""
    key = b"".join([hf.boxes.tobytes(), np.array([hf.seed, ss, step, cam_local.width, cam_local.height]).tobytes(),
                    np.asarray(cam_local.K, float).tobytes(), np.asarray(cam_local.w2c, float).tobytes()])
    if key not in _RENDERED:
        _RENDERED[key] = _march(hf, cam_local, ss, step)
    img, depth = _RENDERED[key]
    return img.copy(), depth.copy()


def _march(hf: HeightField, cam_local: Camera, ss: int, step: float) -> tuple[np.ndarray, np.ndarray]:
    W, H = cam_local.width, cam_local.height
    hi = cam_local.scaled(ss) if ss > 1 else cam_local
    o, d = hi.pixel_rays()
    n = len(d)
    t = np.full(n, np.nan)
    # March from the top of the tallest box downwards; z-depth parameter t.
    zmax = float(hf.boxes[:, 4].max()) + 1.0 if len(hf.boxes) else 1.0
    t_start = np.maximum((o[:, 2] - zmax) / np.maximum(-d[:, 2], 1e-9), 0.0)
    t_end = (o[:, 2] + 1.0) / np.maximum(-d[:, 2], 1e-9)
    tc = t_start.copy()
    prev = tc.copy()
    active = d[:, 2] < -1e-6
    while active.any():
        p = o + d * tc[:, None]
        below = p[:, 2] <= hf.height(p[:, 0], p[:, 1])
        hit = active & below
        if hit.any():  # bisection between prev and tc
            lo, hi_t = prev[hit], tc[hit]
            oo, dd = o[hit], d[hit]
            for _ in range(20):
                mid = 0.5 * (lo + hi_t)
                pm = oo + dd * mid[:, None]
                b = pm[:, 2] <= hf.height(pm[:, 0], pm[:, 1])
                hi_t = np.where(b, mid, hi_t)
                lo = np.where(b, lo, mid)
            t[hit] = hi_t
            active &= ~hit
        prev = tc.copy()
        tc = tc + step
        active &= tc < t_end + step
    t = np.where(np.isnan(t), t_end, t)
    p = o + d * t[:, None]
    col = hf.color(p[:, 0], p[:, 1], p[:, 2]).reshape(H * ss, W * ss, 3)
    img = col.reshape(H, ss, W, ss, 3).mean(axis=(1, 3)).astype(np.float32)
    # Depth at the pixel centre: render without supersampling for exactness.
    if ss > 1:
        _, depth = render(hf, cam_local, ss=1, step=step)
    else:
        depth = t.reshape(H, W).astype(np.float32)
    return img, depth


def rotation_to(up: np.ndarray) -> np.ndarray:
    """A rotation taking +Z to ``up``."""
    up = np.asarray(up, float) / np.linalg.norm(up)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, up)
    c = float(z @ up)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * (1 / (1 + c))


def make_synthetic_scene(size: int = 64, n_views: int = 3, seed: int = 0, radius: float = 50.0,
                         height: float = 110.0, up=(0.0, 0.0, 1.0), offset=(0.0, 0.0, 0.0),
                         fov_deg: float = 50.0, horizontal: bool = False, hf: HeightField | None = None):
    """A Scene with ``n_views`` training views on an orbit (all views are training views).

    ``horizontal=True`` puts the cameras at ground level looking sideways.
    """
    hf = hf or city_heightfield(seed)
    Rw = rotation_to(np.asarray(up, float))  # local z-up -> world
    off = np.asarray(offset, float)
    f = size / 2 / np.tan(np.radians(fov_deg) / 2)
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    views = {}
    for i in range(n_views):
        th = 2 * np.pi * i / n_views + 0.3
        if horizontal:
            eye = np.array([150 * np.cos(th), 150 * np.sin(th), 8.0])
            target = np.array([0.0, 0.0, 8.0])
        else:
            eye = np.array([radius * np.cos(th), radius * np.sin(th), height])
            target = np.zeros(3)
        w2c_local = look_at(eye, target, [0, 0, 1])
        cam_local = Camera(K, w2c_local, size, size, name=f"{i:03d}")
        img, depth = render(hf, cam_local)
        # world = Rw @ local + off  =>  w2c_world = w2c_local @ [Rw^T, -Rw^T off]
        T = np.eye(4)
        T[:3, :3] = Rw.T
        T[:3, 3] = -Rw.T @ off
        near = max(1.0, float(np.nanmin(depth)) * 0.5)
        cam = Camera(K, w2c_local @ T, size, size, name=f"{i:03d}", depth_range=(near, float(np.nanmax(depth)) * 1.5))
        views[f"{i:03d}"] = View(camera=cam, image=img, depth=depth)
    names = sorted(views)
    scene = Scene(root=Path("/nonexistent"), views=views, track=[], train=names, test=[])
    return scene, hf


def make_grid_scene(size: int = 96, n_views: int = 3, spacing: float = 40.0, height: float = 110.0,
                    tilt_deg: float = 1.0, seed: int = 0, fov_deg: float = 50.0, world_scale: float = 1.0,
                    hf: HeightField | None = None):
    """A nadir mapping strip: ``n_views`` cameras ``spacing`` apart along x at ``height``, looking
    straight down up to random tilts of about ``tilt_deg`` (so their axes are nearly parallel and
    meet nowhere in particular, as on a drone's mapping grid). No depth range on the cameras (COLMAP
    scenes have none). ``world_scale`` multiplies every world length (units check)."""
    hf = hf or city_heightfield(seed)
    rng = np.random.default_rng(seed + 1)
    f = size / 2 / np.tan(np.radians(fov_deg) / 2)
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    views = {}
    for i in range(n_views):
        eye = np.array([(i - (n_views - 1) / 2) * spacing, 0.0, height])
        tilt = np.radians(tilt_deg) * rng.normal(size=2)
        target = eye + np.array([np.tan(tilt[0]), np.tan(tilt[1]), -1.0]) * height
        cam_local = Camera(K, look_at(eye, target, [0, 1, 0]), size, size, name=f"{i:03d}")
        img, depth = render(hf, cam_local)
        w2c = cam_local.w2c.copy()
        w2c[:3, 3] *= world_scale
        views[f"{i:03d}"] = View(camera=Camera(K, w2c, size, size, name=f"{i:03d}"), image=img,
                                 depth=depth * world_scale)
    names = sorted(views)
    return Scene(root=Path("/nonexistent"), views=views, track=[], train=names, test=[]), hf


def scaled_scene(scene, factor: float):
    """The same scene with every world length (camera positions, depth ranges, depths) times ``factor``."""
    from dataclasses import replace

    views = {}
    for k, v in scene.views.items():
        w2c = v.camera.w2c.copy()
        w2c[:3, 3] *= factor
        dr = v.camera.depth_range
        cam = replace(v.camera, w2c=w2c, depth_range=None if dr is None else (dr[0] * factor, dr[1] * factor))
        views[k] = View(camera=cam, image=v.image, depth=None if v.depth is None else v.depth * factor)
    return Scene(root=scene.root, views=views, track=list(scene.track), train=list(scene.train), test=list(scene.test))


def nadir(x: float, y: float = 0.0, height: float = 100.0, size: int = 64, name: str = "") -> Camera:
    """A camera ``height`` above (x, y, 0) looking straight down (60 degree field of view)."""
    f = size / 2 / np.tan(np.radians(30))
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    w2c = look_at(np.array([x, y, height]), np.array([x, y, 0.0]), np.array([0, 1.0, 0]))
    return Camera(K=K, w2c=w2c, width=size, height=size, name=name)


def save_tiny_depth_anything(path: Path) -> Path:
    """A Depth Anything V2 model of about 140,000 random weights (instead of 25 million) and its image
    processor, saved with transformers' ``save_pretrained`` to ``path`` (the layout of a local
    download, read back through the pipeline's own loader); returns ``path``."""
    import torch
    from transformers import (
        DepthAnythingConfig,
        DepthAnythingForDepthEstimation,
        Dinov2Config,
        DPTImageProcessor,
    )

    backbone = Dinov2Config(hidden_size=32, num_hidden_layers=4, num_attention_heads=2, intermediate_size=64,
                            patch_size=14, image_size=56, out_features=["stage1", "stage2", "stage3", "stage4"],
                            reshape_hidden_states=False)
    cfg = DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=32, neck_hidden_sizes=[8, 16, 32, 32],
                              fusion_hidden_size=16, head_hidden_size=8, patch_size=14)
    torch.manual_seed(0)
    DepthAnythingForDepthEstimation(cfg).save_pretrained(path)
    DPTImageProcessor(size={"height": 56, "width": 56}, keep_aspect_ratio=True, ensure_multiple_of=14,
                      do_rescale=True, do_normalize=True).save_pretrained(path)
    return path
