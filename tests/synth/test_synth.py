"""Scene generator: a real bpy/Cycles render read back through data.levir, with
ground-truth depth checked for z-depth semantics and multi-view consistency."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from dibrgs_core.camera.frame import estimate_up, nadir_angle_deg
from dibrgs_core.camera.orbit import fit_orbit
from dibrgs_core.data.images import read_depth
from dibrgs_core.data.levir import read_scene
from dibrgs_core.synth.flights import DEFAULT_ORBIT, ORBITS, scene_cameras

pytest.importorskip("bpy")


@pytest.fixture(scope="module")
def scene(tiny_scene):
    return read_scene(tiny_scene)


def test_layout(tiny_scene):
    from PIL import Image

    ids = [f"{i:03d}" for i in range(21)]
    for sub, ext in (("Images", "png"), ("Cams", "txt"), ("Depths", "tiff"), ("Depths", "exr")):
        assert sorted(p.stem for p in (tiny_scene / sub).glob(f"*.{ext}")) == ids, (sub, ext)
    assert len(list((tiny_scene / "Track").glob("*.txt"))) == 60
    with Image.open(tiny_scene / "Images" / "001.png") as im:
        assert (im.mode, im.size) == ("RGB", (64, 64))
    meta = json.loads((tiny_scene / "scene.json").read_text())
    assert (meta["kind"], meta["seed"], meta["resolution"]) == ("city", 0, 64)
    assert not list(tiny_scene.rglob(".*"))  # atomic writes left no temporaries


def test_depth_files_agree_and_cover_view(tiny_scene, scene):
    for vid, v in scene.views.items():
        exr = read_depth(tiny_scene / "Depths" / f"{vid}.exr")
        assert np.array_equal(exr, v.depth)
        assert (v.depth > 0).all(), "the ground plane fills every view"
        lo, hi = v.camera.depth_range
        assert lo < v.depth.min() and v.depth.max() < hi
    assert 100 < scene.views["001"].depth.min() < scene.views["001"].depth.max() < 600
    # Images are textured, not flat.
    assert scene.views["001"].image.std() > 0.05


def test_depth_is_z_depth_not_ray_length(scene):
    """The generated scene's ground is z = 0: back-projecting z-depth puts ground pixels
    exactly on it. Ray length would put them below the ground (off-axis pixels)."""
    for vid in ("000", "001", "011"):
        v = scene.views[vid]
        X = v.camera.backproject(v.depth)
        assert X[:, 2].min() > -1e-2, "nothing lies below the ground"
        ground = np.abs(X[:, 2]) < 1e-2
        assert ground.mean() > 0.3
        o, d = v.camera.pixel_rays()
        unit = d / np.linalg.norm(d, axis=1, keepdims=True)
        as_ray_length = o + unit * v.depth.reshape(-1, 1)
        assert (np.abs(as_ray_length[:, 2]) < 1e-2).mean() < 0.05


def reprojection_errors(scene, a: str, b: str, cam_b=None) -> np.ndarray:
    """Signed relative z disagreement (z_warped - d_b) / d_b when view a's depth is warped
    into view b, on pixels that land inside b where b's depth is locally smooth (bilinear
    lookup, pixel centres at +0.5). Positive = hidden behind b's surface (occluded)."""
    A, B = scene.views[a], scene.views[b]
    cb = cam_b or B.camera
    uv, z = cb.project(A.camera.backproject(A.depth))
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    inside = (x >= 0) & (x <= cb.width - 1) & (y >= 0) & (y <= cb.height - 1) & (z > 0)
    x, y, z = x[inside], y[inside], z[inside]
    d = map_coordinates(B.depth, [y, x], order=1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, cb.width - 1), np.minimum(y0 + 1, cb.height - 1)
    nb = np.stack([B.depth[y0, x0], B.depth[y0, x1], B.depth[y1, x0], B.depth[y1, x1]])
    smooth = (nb.max(0) - nb.min(0)) < 0.03 * nb.min(0)
    assert smooth.sum() > 300
    return ((z - d) / d)[smooth]


@pytest.mark.parametrize("a,b", [("001", "002"), ("002", "001"), ("001", "000"), ("000", "001")])
def test_depth_reprojects_between_views(scene, a, b):
    """A pixel's 3D point from view a lands where view b's depth says: most agree to
    0.5% (median ~1e-5), the rest are occluded in b (behind its surface); almost none
    lands in front of b's surface, which consistent depth maps cannot produce."""
    rel = reprojection_errors(scene, a, b)
    assert np.median(np.abs(rel)) < 1e-3
    assert (np.abs(rel) < 5e-3).mean() > 0.6
    assert (rel < -5e-3).mean() < 0.06  # free-space violations: silhouette pixels only


def test_reprojection_check_detects_wrong_camera(scene):
    """Negative control: with a neighbour's camera in place of the right one, the same
    check fails (many free-space violations, large median error)."""
    for a, b, wrong in (("001", "002", "003"), ("000", "001", "002")):
        rel = reprojection_errors(scene, a, b, cam_b=scene.views[wrong].camera)
        assert np.median(np.abs(rel)) > 5e-3
        assert (rel < -5e-3).mean() > 0.15


def test_acquisition_geometry(scene):
    spec = ORBITS[DEFAULT_ORBIT]
    orbit = [scene.views[f"{i:03d}"].camera for i in range(1, 21)]
    up, conf = estimate_up(orbit)
    assert np.allclose(up, [0, 0, 1], atol=1e-9) and conf > 0.8
    o = fit_orbit(orbit, up)
    assert o.radius == pytest.approx(spec.radius, abs=1e-6) and o.tilt_deg < 1e-6
    assert np.allclose(o.target, 0.0, atol=1e-6)
    assert nadir_angle_deg(orbit, up) == pytest.approx(15.0, abs=1e-6)
    assert nadir_angle_deg([scene.views["000"].camera], up) < 6.0
    t = fit_orbit(scene.track, up)
    assert len(scene.track) == 60 and t.radius == pytest.approx(spec.radius, abs=1e-6)
    # Upright images: image up leans towards world up by the off-nadir angle, with no roll.
    c = orbit[0]
    assert (-c.c2w[:3, 1]) @ up == pytest.approx(math.sin(math.radians(15.0)), abs=1e-6)
    assert abs(c.c2w[:3, 0] @ up) < 1e-9


@pytest.mark.slow
def test_every_kind_renders_and_seed_is_deterministic(tmp_path):
    from dibrgs_core.synth.layout import KINDS
    from dibrgs_core.synth.writer import make_scene

    def render(kind, seed, name):
        out = make_scene(kind, 16, seed, tmp_path / name, samples=4)
        imgs = [np.asarray(read_scene(out, load_depth=True).views[f"{i:03d}"].image) for i in (0, 1, 9)]
        return out, imgs

    outs = {}
    for kind in KINDS:
        out, imgs = render(kind, 0, kind)
        s = read_scene(out)
        assert all((v.depth > 0).mean() > 0.99 for v in s.views.values()), kind
        assert all(im.std() > 0.02 for im in imgs), kind
        outs[kind] = out
    again, _ = render("stadium", 0, "stadium_again")
    for sub, pat in (("Images", "*.png"), ("Depths", "*.tiff"), ("Cams", "*.txt"), ("Track", "*.txt")):
        for p in sorted((outs["stadium"] / sub).glob(pat)):
            assert p.read_bytes() == (again / sub / p.name).read_bytes(), p
    other, _ = render("stadium", 1, "stadium_seed1")
    a = read_scene(outs["stadium"]).views["001"].image
    b = read_scene(other).views["001"].image
    assert np.abs(a - b).mean() > 0.02


def test_make_scene_script_and_info(tmp_path):
    """The CLI script (with Blender-style '--' argument separation) followed by
    `dibrgs info`, as in the issue's acceptance command."""
    import subprocess
    import sys

    from paths import REPO

    out = tmp_path / "s"
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "make_scene.py"), "--", "--kind", "village",
                        "--resolution", "12", "--seed", "3", "--samples", "2", "--out", str(out)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert len(list((out / "Images").glob("*.png"))) == 21
    r = subprocess.run([sys.executable, "-m", "dibrgs_core", "info", str(out)], capture_output=True, text=True,
                       timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stderr[-2000:]
    info = json.loads(r.stdout)
    assert info["views"] == 21 and info["resolution"] == [12, 12]
    assert info["orbit"]["radius"] == pytest.approx(ORBITS["levir"].radius, abs=1e-3)


@pytest.mark.parametrize("name,off_nadir", [("levir", 15.0), ("wide", math.degrees(math.atan2(150, 210)))])
def test_orbit_presets(name, off_nadir):
    """Both named orbits: views 001-020 at the preset's angle off nadir, 18 degrees apart in heading."""
    views, track = scene_cameras(32, 0.7, ORBITS[name])
    up = np.array([0.0, 0.0, 1.0])
    assert ORBITS[name].off_nadir_deg == pytest.approx(off_nadir, abs=1e-9)
    assert nadir_angle_deg(views[1:], up) == pytest.approx(off_nadir, abs=1e-6)
    assert nadir_angle_deg(track, up) == pytest.approx(off_nadir, abs=1e-6)
    a, b = views[1].center[:2], views[2].center[:2]
    heading = math.degrees(math.acos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))
    assert heading == pytest.approx(18.0, abs=1e-6)


def test_unknown_orbit_is_refused(tmp_path):
    from dibrgs_core.synth.writer import make_scene

    with pytest.raises(ValueError, match="orbit must be one of"):
        make_scene("city", 16, 0, tmp_path / "x", orbit="spiral")
    assert not (tmp_path / "x").exists()


def test_grid_flight_layout():
    """The mapping flight: nine near-nadir photos on three strips with the spec's overlaps, flown
    back and forth, the split on the middle photo of each strip, and a Track along the route."""
    from dibrgs_core.camera.trajectory import classify
    from dibrgs_core.synth.flights import GRID, N_TRACK, grid_cameras

    heading = 0.6
    views, track, split = grid_cameras(32, heading, np.random.default_rng(0))
    assert [v.name for v in views] == [f"{i:03d}" for i in range(9)]
    assert split == {"train": ["001", "004", "007"], "test": ["000", "002", "003", "005", "006", "008"]}
    up = np.array([0.0, 0.0, 1.0])
    tilt = [math.degrees(math.acos(-v.c2w[:3, 2] @ up)) for v in views]
    assert 0.1 < max(tilt) < 6.0  # a few degrees off nadir, as a real gimbal
    along = np.array([math.cos(heading), math.sin(heading), 0.0])
    C = np.stack([v.center for v in views])
    assert np.allclose(C[:, 2], GRID.height, rtol=0.1)
    da, dc = GRID.spacing()
    # Neighbours on a strip are one forward step apart; strips one side step apart.
    assert np.allclose(np.abs((C[1] - C[0]) @ along), da, rtol=0.15)
    assert np.allclose(np.abs((C[3] - C[2]) @ np.cross(up, along)), dc, rtol=0.15)
    # Flown back and forth: the second strip runs against the first.
    assert ((C[2] - C[0]) @ along) * ((C[5] - C[3]) @ along) < 0
    # The footprints overlap as specified: 63 % forward, about 1 - 0.37 * 2 at two steps.
    assert 1.0 - da / GRID.footprint() == pytest.approx(GRID.forward_overlap)
    # Image up follows the strips on every strip (the gimbal holds its heading).
    assert all((-v.c2w[:3, 1]) @ along > 0.99 for v in views)
    t = classify([views[i] for i in (1, 4, 7)], up)
    assert t.kind == "strips", t.why
    assert classify(views, up).kind == "strips"
    assert len(track) == N_TRACK
    T = np.stack([c.center for c in track])
    assert np.allclose(T[0], C[0], atol=0.2 * da) and np.allclose(T[-1], C[-1], atol=0.2 * da)
    steps = np.linalg.norm(np.diff(T, axis=0), axis=1)
    # Evenly spread along the route (a step across a turn cuts the corner: shorter, never longer).
    assert steps.max() == pytest.approx(np.median(steps), rel=1e-6) and steps.min() > 0.5 * steps.max()


def test_corridor_and_oblique_flights():
    """The other mapping flights: a corridor (one strip of five, training on every other photo) and
    the block flown with the camera pitched forward (looking at the same ground as the nadir block)."""
    from dibrgs_core.camera.trajectory import classify
    from dibrgs_core.synth.flights import FLIGHTS, GRIDS, grid_cameras

    assert FLIGHTS == ("orbit", "grid", "corridor", "oblique")
    up = np.array([0.0, 0.0, 1.0])
    views, track, split = grid_cameras(32, 0.0, np.random.default_rng(0), GRIDS["corridor"])
    assert [v.name for v in views] == [f"{i:03d}" for i in range(5)]
    assert split == {"train": ["000", "002", "004"], "test": ["001", "003"]}
    assert classify(views, up).kind == "strips" and len(classify(views, up).lines) == 1
    C = np.stack([v.center for v in views])
    assert np.ptp(C[:, 1]) < 0.2 * np.ptp(C[:, 0])  # one line along the heading (+X)

    spec = GRIDS["oblique"]
    heading = 1.1
    along = np.array([math.cos(heading), math.sin(heading), 0.0])
    obl, otrack, osplit = grid_cameras(32, heading, np.random.default_rng(0), spec)
    nad, _, nsplit = grid_cameras(32, heading, np.random.default_rng(0), GRIDS["grid"])
    assert osplit == nsplit
    for o, n in zip(obl, nad):
        d = o.view_dir
        assert math.degrees(math.acos(-d @ up)) == pytest.approx(spec.pitch_deg, abs=6.0)
        assert d @ along > 0.4  # pitched forward along the strips
        # Where the optical axis meets the ground: near the nadir photo's footprint centre.
        hit = o.center + d * (-o.center[2] / d[2])
        assert np.linalg.norm(hit[:2] - n.center[:2]) < 0.15 * spec.footprint()
    assert all(abs(math.degrees(math.acos(-c.view_dir @ up)) - spec.pitch_deg) < 1e-6 for c in otrack)


def test_grid_flight_scene(tmp_path):
    """A rendered grid flight: nine photos, its split.json honoured by the reader, depth everywhere,
    and the same seed's geometry as under the orbit."""
    import bpy

    from dibrgs_core.synth.writer import make_scene

    def vertices():  # the scene make_scene left in the Blender file
        me = bpy.data.objects["objects"].data
        v = np.empty(3 * len(me.vertices))
        me.vertices.foreach_get("co", v)
        return v

    make_scene("village", 16, 2, tmp_path / "orbit", samples=2)
    orbit_geometry = vertices()
    out = make_scene("village", 24, 2, tmp_path / "grid", samples=4, flight="grid")
    assert np.array_equal(vertices(), orbit_geometry) and len(orbit_geometry) > 1000
    s = read_scene(out)
    assert sorted(s.views) == [f"{i:03d}" for i in range(9)]
    assert s.train == ["001", "004", "007"] and s.split_source.endswith("split.json")
    assert s.test == ["000", "002", "003", "005", "006", "008"]
    assert all((v.depth > 0).all() for v in s.views.values())
    meta = json.loads((out / "scene.json").read_text())
    assert meta["flight"] == "grid" and "orbit_name" not in meta
    # Nadir photos 160 m above flat ground: the ground's depth is close to the flight height.
    d = np.concatenate([v.depth.ravel() for v in s.views.values()])
    assert 140 < np.median(d) < 175
    with pytest.raises(ValueError, match="flight must be one of"):
        make_scene("city", 16, 0, tmp_path / "y", flight="spiral")
    assert not (tmp_path / "y").exists()
