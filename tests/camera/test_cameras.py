"""Cameras: exact convention round trips, Blender agreement, up axis and orbit fit."""
from __future__ import annotations

import math

import numpy as np
import pytest

from dibrgs_core.camera.blender import BlenderCameraParams, from_blender, to_blender
from dibrgs_core.camera.pinhole import Camera, look_at, rigid_inverse
from dibrgs_core.camera.serialize import camera_from_dict, camera_to_dict
from dibrgs_core.camera.frame import estimate_up, nadir_angle_deg, up_frame
from dibrgs_core.camera.orbit import fit_orbit

FITS = ("AUTO", "HORIZONTAL", "VERTICAL")


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def random_camera(rng: np.random.Generator, name: str = "cam") -> Camera:
    """Non-square image, fx != fy, principal point well off centre."""
    W, H = int(rng.integers(17, 900)), int(rng.integers(17, 900))
    fx = rng.uniform(0.4, 3.0) * max(W, H)
    fy = fx * rng.uniform(0.7, 1.4)
    cx = W / 2 + rng.uniform(-0.3, 0.3) * W
    cy = H / 2 + rng.uniform(-0.3, 0.3) * H
    w2c = np.eye(4)
    w2c[:3, :3] = random_rotation(rng)
    w2c[:3, 3] = rng.normal(scale=100.0, size=3)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return Camera(K=K, w2c=w2c, width=W, height=H, name=name, depth_range=(0.5, 900.0))


def points_in_front(cam: Camera, rng: np.random.Generator, n: int = 50) -> np.ndarray:
    uv = rng.uniform([0, 0], [cam.width, cam.height], size=(n, 2))
    z = rng.uniform(1.0, 500.0, n)
    xc = np.stack([(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z], 1)
    return (xc - cam.t) @ cam.R  # R^T (xc - t)


# -- OpenCV <-> Blender -------------------------------------------------------
@pytest.mark.parametrize("fit", FITS)
def test_blender_round_trip_exact(fit):
    rng = np.random.default_rng(1)
    for k in range(200):
        cam = random_camera(rng, f"{k:03d}")
        p = to_blender(cam, sensor_width=float(rng.uniform(10, 50)), sensor_fit=fit)
        back = from_blender(p, depth_range=True)
        assert np.abs(back.K - cam.K).max() <= 1e-9 * max(1.0, np.abs(cam.K).max())
        assert np.abs(back.w2c - cam.w2c).max() <= 1e-9 * max(1.0, np.abs(cam.w2c).max())
        assert (back.width, back.height, back.name) == (cam.width, cam.height, cam.name)
        assert back.depth_range == pytest.approx(cam.depth_range, abs=1e-12)
        assert p.pixel_aspect_x >= 1.0 and p.pixel_aspect_y >= 1.0
        assert min(p.pixel_aspect_x, p.pixel_aspect_y) == 1.0


def test_blender_matrix_world_axes():
    """Blender's camera looks down its local -Z with +Y up: check against the OpenCV axes."""
    rng = np.random.default_rng(2)
    cam = random_camera(rng)
    M = to_blender(cam).matrix_world
    assert np.allclose(-M[:3, 2], cam.view_dir, atol=1e-12)      # -Z_blender = forward
    assert np.allclose(M[:3, 1], -cam.c2w[:3, 1], atol=1e-12)    # +Y_blender = image up = -y_cv
    assert np.allclose(M[:3, 3], cam.center, atol=1e-9)


def test_skewed_K_rejected():
    cam = random_camera(np.random.default_rng(3))
    cam.K[0, 1] = 2.0
    with pytest.raises(ValueError, match="skew"):
        to_blender(cam)


def _bpy_camera(bpy, p: BlenderCameraParams):
    """A real bpy camera object and scene configured from ``p``."""
    from mathutils import Matrix

    sc = bpy.data.scenes.new("cam_test")
    data = bpy.data.cameras.new("cam_test")
    ob = bpy.data.objects.new("cam_test", data)
    sc.collection.objects.link(ob)
    sc.camera = ob
    data.lens, data.sensor_width, data.sensor_height, data.sensor_fit = p.lens, p.sensor_width, \
        p.sensor_height, p.sensor_fit
    data.shift_x, data.shift_y = p.shift_x, p.shift_y
    data.clip_start, data.clip_end = 1e-3, 1e6
    r = sc.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = p.resolution_x, p.resolution_y, 100
    r.pixel_aspect_x, r.pixel_aspect_y = p.pixel_aspect_x, p.pixel_aspect_y
    ob.matrix_world = Matrix([list(map(float, row)) for row in p.matrix_world])
    bpy.context.view_layer.update()
    return sc, ob


@pytest.mark.parametrize("fit", FITS)
def test_projection_matches_real_blender_camera(fit):
    """Points projected by Blender (world_to_camera_view on a real camera object) land
    where Camera.project puts them; the parameters read back from bpy invert exactly."""
    bpy = pytest.importorskip("bpy")
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    rng = np.random.default_rng(10 + FITS.index(fit))
    for _ in range(6):
        cam = random_camera(rng)
        p = to_blender(cam, sensor_width=36.0, sensor_fit=fit)
        sc, ob = _bpy_camera(bpy, p)
        try:
            X = points_in_front(cam, rng)
            uv, z = cam.project(X)
            for x, u, d in zip(X, uv, z):
                ndc = world_to_camera_view(sc, ob, Vector(x.tolist()))
                # Blender: (0,0) bottom-left, (1,1) top-right of the frame; z = distance along -Z;
                # float32 inside Blender, hence the 0.02 px tolerance.
                assert ndc.x * cam.width == pytest.approx(u[0], abs=0.02)
                assert (1.0 - ndc.y) * cam.height == pytest.approx(u[1], abs=0.02)
                assert ndc.z == pytest.approx(d, rel=1e-5)
            # Read the parameters back from the bpy objects. Blender stores and projects in
            # float32, hence 0.02 px tolerance (a convention error is >= 0.5 px).
            d = ob.data
            back = from_blender(BlenderCameraParams(
                matrix_world=np.array(ob.matrix_world), lens=d.lens, sensor_width=d.sensor_width,
                sensor_height=d.sensor_height, sensor_fit=d.sensor_fit, shift_x=d.shift_x, shift_y=d.shift_y,
                resolution_x=sc.render.resolution_x, resolution_y=sc.render.resolution_y,
                pixel_aspect_x=sc.render.pixel_aspect_x, pixel_aspect_y=sc.render.pixel_aspect_y))
            uv2, _ = back.project(X)
            assert np.abs(uv2 - uv).max() < 0.02
        finally:
            bpy.data.objects.remove(ob)
            bpy.data.scenes.remove(sc)


# -- projection, scaling, JSON --------------------------------------------------
def test_project_backproject_and_pixel_centres():
    rng = np.random.default_rng(4)
    cam = random_camera(rng)
    depth = rng.uniform(1, 300, (cam.height, cam.width))
    X = cam.backproject(depth)
    uv, z = cam.project(X)
    j, i = np.meshgrid(np.arange(cam.height) + 0.5, np.arange(cam.width) + 0.5, indexing="ij")
    assert np.allclose(uv, np.stack([i.ravel(), j.ravel()], 1), atol=1e-7)
    assert np.allclose(z, depth.ravel(), rtol=1e-12)
    assert np.allclose(cam.center, cam.c2w[:3, 3]) and np.allclose(cam.c2w @ cam.w2c, np.eye(4), atol=1e-12)
    assert np.allclose(rigid_inverse(rigid_inverse(cam.w2c)), cam.w2c, atol=1e-12)


def test_scaled_keeps_pixel_centres():
    cam = Camera(K=[[100, 0, 32], [0, 100, 24], [0, 0, 1]], w2c=np.eye(4), width=64, height=48)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (32, 24)
    X = np.array([[1.0, -2.0, 50.0]])
    assert np.allclose(half.project(X)[0], cam.project(X)[0] * 0.5)


def test_translated_sees_the_moved_world_alike():
    """``translated(d)``: the camera of a world moved by ``d`` sees ``X + d`` where it saw ``X``;
    ``translated(-d)`` takes it back; local_origin moves only scenes far from their origin."""
    from dibrgs_core.data.scene import local_origin

    rng = np.random.default_rng(7)
    cam = random_camera(rng)
    d = np.array([3.0e6, -2.0e6, 5.0e6])
    moved = cam.translated(d)
    X = cam.backproject(rng.uniform(1, 300, (cam.height, cam.width)))[:50]
    assert np.allclose(moved.center, cam.center + d) and np.array_equal(moved.R, cam.R)
    assert np.allclose(moved.project(X + d)[0], cam.project(X)[0], atol=1e-6)
    assert np.allclose(moved.translated(-d).w2c, cam.w2c, atol=1e-6)
    cams = [random_camera(rng) for _ in range(4)]
    assert not local_origin(cams).any()  # centres within 100 x their spread of the origin
    far = local_origin([c.translated(d) for c in cams])
    C = np.stack([c.center for c in cams])
    assert np.linalg.norm(far - (d + C.mean(axis=0))) <= np.sqrt(((C - C.mean(axis=0)) ** 2).sum(1).mean())
    assert not local_origin([cams[0], cams[0]]).any()  # no spread: nothing to measure "far" against


def test_camera_dict_round_trip_and_errors():
    rng = np.random.default_rng(5)
    cam = random_camera(rng, "v7")
    back = camera_from_dict(camera_to_dict(cam))
    assert np.array_equal(back.K, cam.K) and np.array_equal(back.w2c, cam.w2c)
    assert (back.width, back.height, back.name, back.depth_range) == (cam.width, cam.height, "v7", cam.depth_range)
    d = camera_to_dict(cam)
    d["K"][0][0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        camera_from_dict(d, "x.json")
    with pytest.raises(ValueError, match="x.json"):
        camera_from_dict({"name": "a"}, "x.json")


def test_look_at_degenerate_and_orientation():
    w2c = look_at([0, 0, 100], [0, 0, 0], [0, 0, 1])  # looking straight along -up
    cam = Camera(K=np.eye(3), w2c=w2c, width=1, height=1)
    assert np.allclose(cam.view_dir, [0, 0, -1])
    assert abs(np.linalg.det(w2c[:3, :3]) - 1) < 1e-12
    w2c = look_at([100, 0, 100], [0, 0, 0], [0, 0, 1])
    cam = Camera(K=np.eye(3), w2c=w2c, width=1, height=1)
    # Image "up" (-y) points towards world +Z.
    assert (-cam.c2w[:3, 1]) @ np.array([0, 0, 1.0]) > 0.5
    with pytest.raises(ValueError):
        look_at([1, 2, 3], [1, 2, 3], [0, 0, 1])


# -- up axis and orbit --------------------------------------------------------
def synthetic_orbit(rng, n=20, radius=150.0, height=210.0, up=None, tilt_deg=0.0, center=None):
    """Cameras on a circle (possibly tilted w.r.t. ``up``) looking at ``center``."""
    up = np.array([0, 0, 1.0]) if up is None else np.asarray(up, float) / np.linalg.norm(up)
    center = np.zeros(3) if center is None else np.asarray(center, float)
    F = up_frame(up)  # rows e1, e2, up
    t = math.radians(tilt_deg)
    normal = math.cos(t) * F[2] + math.sin(t) * F[0]
    b1 = np.cross(normal, F[1])
    b1 /= np.linalg.norm(b1)
    b2 = np.cross(normal, b1)
    circle_c = center + height * up
    th = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n) / n
    K = np.array([[300, 0, 128], [0, 300, 128], [0, 0, 1.0]])
    cams = [Camera(K=K, w2c=look_at(circle_c + radius * (math.cos(a) * b1 + math.sin(a) * b2), center, up),
                   width=256, height=256, name=f"{i:03d}") for i, a in enumerate(th)]
    return cams, circle_c, normal


def test_estimate_up_not_assuming_z():
    rng = np.random.default_rng(6)
    up = random_rotation(rng) @ np.array([0, 0, 1.0])
    cams, _, _ = synthetic_orbit(rng, up=up)
    est, conf = estimate_up(cams)
    assert np.allclose(est, up, atol=1e-9)
    assert 0.5 < conf <= 1.0
    off = math.degrees(math.atan2(150, 210))
    assert nadir_angle_deg(cams) == pytest.approx(off, abs=1e-6)


def test_estimate_up_ambiguous():
    """Cameras looking in all directions: confidence near 0."""
    K = np.eye(3)
    dirs = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    cams = [Camera(K=K, w2c=look_at([0, 0, 0], d, [0.3, 0.5, 0.7]), width=1, height=1) for d in dirs]
    _, conf = estimate_up(cams)
    assert conf < 1e-9


@pytest.mark.parametrize("tilt", [0.0, 12.0])
def test_fit_orbit_recovers_circle(tilt):
    rng = np.random.default_rng(7)
    up = random_rotation(rng) @ np.array([0, 0, 1.0])
    center = rng.normal(scale=50, size=3)
    cams, circle_c, normal = synthetic_orbit(rng, radius=123.0, height=180.0, up=up, tilt_deg=tilt,
                                             center=center)
    o = fit_orbit(cams, up=up)
    assert o.radius == pytest.approx(123.0, abs=1e-6)
    assert np.allclose(o.center, circle_c, atol=1e-6)
    assert np.allclose(o.normal, normal, atol=1e-9)
    assert o.tilt_deg == pytest.approx(tilt, abs=1e-6)
    assert np.allclose(o.target, center, atol=1e-6)
    assert o.rms < 1e-6
    # Orbit cameras regenerate the input poses' centres.
    regen = o.cameras(o.angle_of(np.stack([c.center for c in cams])), like=cams[0])
    assert np.allclose([c.center for c in regen], [c.center for c in cams], atol=1e-6)


def test_fit_orbit_noisy_and_small():
    rng = np.random.default_rng(8)
    cams, circle_c, _ = synthetic_orbit(rng, radius=100.0, height=100.0)
    for c in cams:  # jitter camera positions by ~0.5 units
        c.w2c[:3, 3] += rng.normal(scale=0.5, size=3)
    o = fit_orbit(cams)
    assert o.radius == pytest.approx(100.0, rel=0.02)
    assert np.linalg.norm(o.center - circle_c) < 2.0
    assert 0.05 < o.rms < 2.0
    two = fit_orbit(cams[:2])  # fewer than 3: plane perpendicular to up, still finite
    assert np.isfinite(two.radius) and np.isfinite(two.center).all()
    with pytest.raises(ValueError):
        fit_orbit(cams[:1])


def test_unproject_inverts_project():
    rng = np.random.default_rng(1)
    K = np.array([[300.0, 2.0, 160.0], [0.0, 310.0, 120.0], [0.0, 0.0, 1.0]])  # with skew
    cam = Camera(K=K, w2c=look_at(np.array([5.0, -40.0, 30.0]), np.zeros(3), np.array([0, 0, 1.0])), width=320,
                 height=240)
    X = rng.uniform(-10, 10, (100, 3))
    uv, z = cam.project(X)
    np.testing.assert_allclose(cam.unproject(uv, z), X, atol=1e-9)


def test_span_is_the_views_width_per_unit_of_depth():
    """2 tan(fov / 2) for a square image, the geometric mean of both sides otherwise; the same at any
    image size (a resized photo covers the same ground)."""
    from dibrgs_core.camera.frame import REFERENCE_SPAN, span_factor

    f = 128 / np.tan(np.radians(25.0))
    cam = Camera(K=np.array([[f, 0, 128], [0, f, 128], [0, 0, 1.0]]), w2c=np.eye(4), width=256, height=256)
    assert cam.span == pytest.approx(2 * np.tan(np.radians(25.0)), rel=1e-12)
    assert cam.scaled(0.5).span == pytest.approx(cam.span, rel=1e-12)
    wide = Camera(K=np.array([[661.2, 0, 476.5], [0, 661.2, 268.0], [0, 0, 1.0]]), w2c=np.eye(4), width=953, height=536)
    assert wide.span == pytest.approx(np.sqrt(953 / 661.2 * 536 / 661.2), rel=1e-12)  # brighton_north's photos
    assert span_factor([wide, wide, cam]) == pytest.approx(wide.span / REFERENCE_SPAN)
    ref = Camera(K=np.array([[35 / 36 * 256, 0, 128], [0, 35 / 36 * 256, 128], [0, 0, 1.0]]), w2c=np.eye(4),
                 width=256, height=256)
    assert span_factor([ref]) == 1.0  # exactly: the generated scenes keep their thresholds to the bit
