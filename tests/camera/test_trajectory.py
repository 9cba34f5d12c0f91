"""Tests for dibrgs_core.camera.trajectory: rotations, trajectory classes, pose sampling."""
from __future__ import annotations

import numpy as np
import pytest

from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.camera.rotations import axis_angle, quat_of, rot_of, slerp
from dibrgs_core.camera.trajectory import classify, sample_poses

K = np.array([[300.0, 0, 160], [0, 300.0, 90], [0, 0, 1]])


def nadir(x: float, y: float, h: float = 5.3, yaw_deg: float = 0.0, name: str = "") -> Camera:
    """A camera at (x, y, h) looking straight down (+Z up), image x along world x turned by ``yaw``."""
    a = np.radians(yaw_deg)
    fwd = np.array([-np.sin(a), np.cos(a), 0.0])  # image up
    return Camera(K=K, w2c=look_at([x, y, h], [x, y, 0.0], fwd), width=320, height=180, name=name)


def orbit_cams(n: int = 3, radius: float = 56.0, height: float = 210.0, start: int = 0, step: int = 7):
    out = []
    for k in range(n):
        a = 2 * np.pi * (start + k * step) / 20
        out.append(Camera(K=K, w2c=look_at([radius * np.cos(a), radius * np.sin(a), height], [0, 0, 0], [0, 0, 1]),
                          width=320, height=180, name=f"o{k}"))
    return out


def angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def transformed(cams, scale: float, offset) -> list[Camera]:
    """The same cameras in other units and another origin (world X -> scale X + offset)."""
    out = []
    for c in cams:
        w2c = c.w2c.copy()
        w2c[:3, 3] = -c.R @ (scale * c.center + np.asarray(offset, float))
        out.append(Camera(K=c.K, w2c=w2c, width=c.width, height=c.height, name=c.name))
    return out


def test_quaternions_and_slerp():
    rng = np.random.default_rng(0)
    for _ in range(50):
        R = axis_angle(rng.normal(size=3), rng.uniform(0, np.pi))
        assert np.allclose(rot_of(quat_of(R)), R, atol=1e-12)
    Ra, Rb = axis_angle([0, 0, 1], 0.2), axis_angle([1, 1, 0], 1.4) @ axis_angle([0, 0, 1], 0.2)
    assert np.allclose(slerp(Ra, Rb, 0.0), Ra) and np.allclose(slerp(Ra, Rb, 1.0), Rb)
    full = angle_deg(Ra, Rb)
    for t in (0.25, 0.5, 0.8):
        Rt = slerp(Ra, Rb, t)
        assert angle_deg(Ra, Rt) == pytest.approx(t * full, abs=1e-6)
        assert angle_deg(Rt, Rb) == pytest.approx((1 - t) * full, abs=1e-6)
    assert np.allclose(slerp(Ra, Ra, 0.3), Ra)


def test_a_levir_orbit_is_an_orbit_and_poses_lie_on_it():
    cams = orbit_cams()
    t = classify(cams)
    assert t.kind == "orbit" and "look towards its axis" in t.reason
    assert t.orbit.radius == pytest.approx(56.0, rel=1e-6)
    poses = sample_poses(t, cams, 40, seed=1, jitter=0.0, look_deg=0.0)
    for p in poses:
        d = p.center - t.orbit.center
        assert abs(np.linalg.norm(d - (d @ t.orbit.normal) * t.orbit.normal) - 56.0) < 1e-6
        uv, z = p.project(t.orbit.target[None])
        assert z[0] > 0 and np.allclose(uv[0], [160, 90], atol=1e-6)
    thetas = np.array([t.orbit.angle_of(p.center) for p in poses])
    assert np.ptp(np.unwrap(np.sort(thetas))) > 1.5 * np.pi  # the whole circle, as the paper samples it
    # Jitter moves poses off the circle by about jitter x min(spacing, radius), and tilts them a little.
    jit = sample_poses(t, cams, 200, seed=1, jitter=0.1, look_deg=2.0)
    off = np.array([abs(np.linalg.norm(p.center[:2]) - 56.0) for p in jit])
    assert 1.0 < np.median(off) < 10.0
    tilts = [angle_deg(a.R, b.R) for a, b in zip(sample_poses(t, cams, 50, 2, 0.1, 0.0),
                                                 sample_poses(t, cams, 50, 2, 0.1, 2.0))]
    assert 0.3 < np.median(tilts) < 5.0


def test_one_photo_per_strip_is_a_straight_line_and_poses_stay_on_it():
    """brighton_north's split: the middle photo of each of three strips, ~3 units apart at 5.3 high."""
    cams = [nadir(-3.08, 2.17, name="a"), nadir(-0.13, 2.50, name="b"), nadir(2.81, 2.42, name="c")]
    t = classify(cams)
    assert t.kind == "strips" and len(t.lines) == 1 and "one straight line" in t.reason
    assert t.lines[0] in ([0, 1, 2], [2, 1, 0])
    poses = sample_poses(t, cams, 200, seed=0, jitter=0.0, look_deg=0.0)
    xs = np.array([p.center[0] for p in poses])
    # Between the cameras and half a spacing past the ends, never beyond.
    assert xs.min() < -3.08 - 0.5 and xs.max() > 2.81 + 0.5
    assert xs.min() > -3.08 - 0.5 * 2.95 - 1e-6 and xs.max() < 2.81 + 0.5 * 2.95 + 1e-6
    C = np.stack([c.center for c in cams])
    for p in poses:  # on the polyline through the cameras, nadir like them
        k = np.clip(np.searchsorted(C[:, 0], p.center[0]), 1, 2)
        a, b = C[k - 1], C[k]
        s = (p.center[0] - a[0]) / (b[0] - a[0])
        assert np.allclose(p.center, a + s * (b - a), atol=1e-9)
        assert p.view_dir[2] < -0.999
    # With jitter, every pose stays within a few spacings' tenths of the line.
    jit = sample_poses(t, cams, 200, seed=0)
    dy = np.array([p.center[1] for p in jit]) - np.interp([p.center[0] for p in jit], C[:, 0], C[:, 1])
    assert 0.05 < np.std(dy) < 0.6


def test_one_photo_per_strip_also_samples_along_the_strips():
    """The cameras face across their line (image up along the strips, as a mapping flight flies):
    with the scene's depth known, poses also run along each camera's heading, half the image's
    ground extent either way, and take half the draws; a corridor (cameras facing along their
    line) and an unknown depth add none."""
    cams = [nadir(-3.08, 2.17, name="a"), nadir(-0.13, 2.50, name="b"), nadir(2.81, 2.42, name="c")]
    t = classify(cams, scene_depth=5.3)
    assert t.kind == "strips" and "one photo a strip" in t.reason
    heads = [sg for sg in t.segments if sg.direction is not None]
    reach = 0.5 * 180 / 300.0 * 5.3
    assert len(heads) == 3 and all(np.allclose(sg.direction, [0.0, reach, 0.0]) for sg in heads)
    poses = sample_poses(t, cams, 400, seed=0, jitter=0.0, look_deg=0.0)
    C = np.stack([c.center for c in cams])
    off_line = [p for p in poses if np.min(np.abs(p.center[0] - C[:, 0])) < 1e-9
                and np.min(np.linalg.norm(p.center - C, axis=1)) > 1e-6]
    assert 0.4 < len(off_line) / len(poses) < 0.6
    for p in off_line:  # along a camera's heading, within reach, with that camera's rotation
        k = int(np.argmin(np.abs(p.center[0] - C[:, 0])))
        assert abs(p.center[1] - C[k, 1]) <= reach + 1e-9 and np.allclose(p.R, cams[k].R)
    corridor = [nadir(0.0, y) for y in (0.0, 1.6, 3.2)]
    assert all(sg.direction is None for sg in classify(corridor, scene_depth=5.3).segments)
    assert all(sg.direction is None for sg in classify(cams).segments)
    # A photo stored turned a quarter (its image up along the line): the other two decide, and its
    # heading is square to the line, as far as its image's width reaches.
    turned = [cams[0], nadir(-0.13, 2.50, yaw_deg=90.0, name="b"), cams[2]]
    t = classify(turned, scene_depth=5.3)
    assert "one photo a strip" in t.reason and "2 of the 3 cameras face" in t.reason
    heads = [sg.direction for sg in t.segments if sg.direction is not None]
    assert len(heads) == 3 and np.allclose(heads[0], [0.0, reach, 0.0]) and np.allclose(heads[2], [0.0, reach, 0.0])
    line = np.array(t.lines[0])
    along = C[line[-1]] - C[line[0]]
    assert np.isclose(np.linalg.norm(heads[1]), 0.5 * 320 / 300.0 * 5.3) and heads[1][2] == 0.0
    assert abs(heads[1] @ along) < 0.05 * np.linalg.norm(heads[1]) * np.linalg.norm(along)  # square to the line
    # two of three turned look like a corridor's cameras: no headings
    two = [cams[0], nadir(-0.13, 2.50, yaw_deg=90.0), nadir(2.81, 2.42, yaw_deg=-90.0)]
    assert all(sg.direction is None for sg in classify(two, scene_depth=5.3).segments)


def test_a_mapping_grid_is_parallel_strips():
    cams = [nadir(x, y, name=f"{x}{y}") for x in (-3.0, 0.0, 3.0) for y in (0.6, 2.2, 3.8)]
    t = classify(cams)
    assert t.kind == "strips" and len(t.lines) == 3 and "3 parallel straight lines" in t.reason
    assert sorted(len(line) for line in t.lines) == [3, 3, 3]
    two = [nadir(x, y) for x in (-3.0, 0.0, 3.0) for y in (0.6, 2.2)]
    assert classify(two).kind == "strips" and len(classify(two).lines) == 3
    poses = sample_poses(t, cams, 300, seed=3, jitter=0.0, look_deg=0.0)
    P = np.array([p.center[:2] for p in poses])
    # Along the strips (x fixed) and across them between neighbours (y fixed).
    on_strip = np.min(np.abs(P[:, :1] - np.array([[-3.0, 0.0, 3.0]])), axis=1) < 1e-9
    across = np.min(np.abs(P[:, 1:] - np.array([[0.6, 2.2, 3.8]])), axis=1) < 1e-9
    assert on_strip.mean() > 0.3 and across.mean() > 0.1 and (on_strip | across).all()


def test_scattered_cameras_are_free_and_chords_of_a_circle_are_no_grid():
    cams = [nadir(0, 0), nadir(3.1, 0.4), nadir(0.8, 2.9), nadir(4.0, 3.5), nadir(-2.5, 2.0)]
    t = classify(cams)
    assert t.kind == "free" and "neighbouring cameras" in t.reason
    poses = sample_poses(t, cams, 100, seed=0, jitter=0.0, look_deg=0.0)
    C = np.stack([c.center for c in cams])
    for p in poses:  # on a segment between two neighbours
        best = min(np.linalg.norm(np.cross(p.center - C[s.a], C[s.b] - C[s.a])) / np.linalg.norm(C[s.b] - C[s.a])
                   for s in t.segments)
        assert best < 1e-9
    # 20 nadir cameras on a circle pair up into parallel chords of every length: an orbit, not a grid.
    ring = [nadir(10 * np.cos(a), 10 * np.sin(a)) for a in np.linspace(0, 2 * np.pi, 20, endpoint=False)]
    assert classify(ring).kind == "orbit"
    # Three nadir cameras off a line: a circle fits any three points, so that is no orbit.
    assert classify(cams[:3]).kind == "free"
    # Two photos from one place and a third elsewhere: two positions on a line, not "one position"
    # (the spacing is to the nearest *other* position, not 0).
    twice = classify([nadir(0, 0), nadir(0, 0), nadir(5.0, 0)])
    assert twice.kind == "strips" and twice.spacing == pytest.approx(5.0)
    assert classify([nadir(1, 2), nadir(1, 2)]).reason.startswith("the cameras share one position")


@pytest.mark.stability
@pytest.mark.parametrize("scale,offset", [(1e-3, (0, 0, 0)), (1e3, (0, 0, 0)), (1.0, (4e5, -5e6, 120.0))])
def test_classes_and_poses_do_not_depend_on_units_or_origin(scale, offset):
    """An orbit, a row of three nadir photos and a 3x3 grid, scaled by 1e-3..1e3 and moved: the same
    trajectory class and flight lines, spacings and pseudo poses scaled and moved alike."""
    sets = [orbit_cams(), [nadir(-3.08, 2.17), nadir(-0.13, 2.50), nadir(2.81, 2.42)],
            [nadir(x, y) for x in (-3.0, 0.0, 3.0) for y in (0.6, 2.2, 3.8)]]
    for cams in sets:
        a, b = classify(cams, scene_depth=5.3), classify(transformed(cams, scale, offset), scene_depth=5.3 * scale)
        assert a.kind == b.kind and a.lines == b.lines
        assert b.spacing == pytest.approx(scale * a.spacing, rel=1e-6)
        pa, pb = sample_poses(a, cams, 20, 5), sample_poses(b, transformed(cams, scale, offset), 20, 5)
        for x, y in zip(pa, pb):
            assert np.allclose(scale * x.center + np.asarray(offset), y.center, rtol=1e-9, atol=1e-6 * scale)
            assert np.allclose(x.R, y.R, atol=1e-6)


def test_a_telephoto_orbit_jitters_by_the_same_share_of_its_view():
    """The orbit seen from 100 x further through a 100 x longer lens (a satellite's view): jitter in
    position and look direction moves the orbit's target across the image by the same share of it as
    for the near orbit. Taken from the distances and in degrees, it threw the target 2-3 images away."""
    tele = K.copy()
    tele[0, 0] *= 100.0
    tele[1, 1] *= 100.0
    near = orbit_cams()
    far = [Camera(K=tele, w2c=look_at(100 * c.center, [0, 0, 0], [0, 0, 1]), width=320, height=180, name=c.name)
           for c in near]
    shifts = {}
    for name, cams in (("near", near), ("far", far)):
        t = classify(cams)
        uv = np.array([p.project(t.orbit.target[None])[0][0] for p in sample_poses(t, cams, 200, 3)])
        shifts[name] = np.median(np.linalg.norm(uv - [160, 90], axis=1)) / 320
    assert 0.005 < shifts["near"] < 0.2 and 0.5 < shifts["far"] / shifts["near"] < 2.0, shifts


def test_sampling_is_seeded_and_prefix_stable():
    cams = [nadir(-3.0, 2.2), nadir(0.0, 2.5), nadir(3.0, 2.4)]
    t = classify(cams)
    a, b = sample_poses(t, cams, 10, 7), sample_poses(t, cams, 30, 7)
    assert all(np.allclose(x.w2c, y.w2c) for x, y in zip(a, b))
    assert not np.allclose(sample_poses(t, cams, 1, 8)[0].w2c, a[0].w2c)
    assert [p.name for p in a] == [f"pseudo_{i:03d}" for i in range(10)]
    assert all(np.array_equal(p.K, K) and (p.width, p.height) == (320, 180) for p in a)
    assert sample_poses(t, cams, 0, 7) == []
    single = classify(cams[:1], scene_depth=5.3)
    quarter = 5.3 / 4 * cams[0].span / (36 / 35)  # a quarter of the ground the view covers, for the reference lens
    assert single.kind == "free" and single.spacing == pytest.approx(quarter)
    assert len(sample_poses(single, cams[:1], 3, 0)) == 3
    # Cameras at one position (a panning camera): jitter from the scene depth, not from units.
    pan = [Camera(K=K, w2c=look_at([1e3, 0, 5.3], [1e3 + dx, 1, 0], [0, 0, 1]), width=320, height=180)
           for dx in (-1.0, 0.0, 1.0)]
    t_pan = classify(pan, scene_depth=5.3)
    assert t_pan.kind == "free" and t_pan.spacing == pytest.approx(quarter) and "one position" in t_pan.reason
    offs = [np.linalg.norm(p.center - pan[0].center) for p in sample_poses(t_pan, pan, 50, 0)]
    assert 0.02 < np.median(offs) < 0.5


def test_brighton_north_flight():
    """The real flight: its three training cameras lie on one line; all nine photos form three strips."""
    from paths import shared_file
    from dibrgs_core.data.colmap import read_colmap_cameras

    cams = {c.name: c for c in read_colmap_cameras(shared_file("data/brighton_north"))}
    t = classify([cams[k] for k in ("DJI_0019", "DJI_0028", "DJI_0031")])
    assert t.kind == "strips" and len(t.lines) == 1
    t9 = classify(list(cams.values()))
    assert t9.kind == "strips" and sorted(len(x) for x in t9.lines) == [3, 3, 3]
