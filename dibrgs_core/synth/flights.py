"""How a generated scene is photographed (NumPy, no bpy): the acquisition flights and their cameras.

World units are metres, the ground is the plane z = 0 and +Z is up *in the generated scenes
only* (the library estimates up from the cameras). OpenCV cameras, world-to-camera
(:mod:`..camera.pinhole`).

* ``orbit`` flights: view 000 looks down near nadir; views 001-020 sit on a horizontal circular
  orbit looking at the scene centre: 15 degrees off nadir by default (orbit ``levir``), or 35.5
  degrees (orbit ``wide``, a stiffer case with heavy occlusion between views 126 degrees apart).
* mapping flights (:data:`GRIDS`): photos on parallel strips (:class:`GridSpec`): ``grid``
  (nadir, the real flight's block), ``corridor`` (one strip), ``oblique`` (pitched forward).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..camera.pinhole import Camera, look_at
from ..camera.rotations import axis_angle

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


@dataclass(frozen=True)
class GridSpec:
    """A mapping flight over a generated scene (metres, degrees): ``strips`` parallel strips of
    ``per_strip`` photos flown back and forth, the camera's yaw fixed (image up along the strips on
    every strip, as a gimbal holding its heading does), pitched ``pitch_deg`` forward off nadir.

    The defaults copy ``brighton_north``'s northern block: three strips of three photos,
    63 % forward and 62 % side overlap (of a nadir photo's footprint), the attitude a few
    degrees off nadir.
    """

    strips: int = 3
    per_strip: int = 3
    height: float = 160.0          # above the ground plane z = 0
    forward_overlap: float = 0.63  # along a strip, as a share of a nadir footprint
    side_overlap: float = 0.62     # between strips
    pitch_deg: float = 0.0         # optical axis tilted forward along the strips (0: nadir)
    tilt_deg: float = 1.5          # attitude noise (standard deviation of each tilt axis)
    jitter: float = 0.03           # position noise, as a share of the photo spacing
    lens_mm: float = 35.0
    sensor_mm: float = 36.0

    def footprint(self) -> float:
        """Side of a nadir photo's footprint on the ground (square images), metres."""
        return self.height * self.sensor_mm / self.lens_mm

    def spacing(self) -> tuple[float, float]:
        """(along a strip, between strips) distances of the photos, metres."""
        f = self.footprint()
        return (1.0 - self.forward_overlap) * f, (1.0 - self.side_overlap) * f

    def train_indices(self) -> list[int]:
        """Training photos of the sparse-view split, by flight-order index: the middle photo of each
        strip (as ``brighton_north``), or every other photo of a single strip."""
        if self.strips == 1:
            return list(range(0, self.per_strip, 2))
        return [i * self.per_strip + self.per_strip // 2 for i in range(self.strips)]


#: Mapping flights by name (``make_scene(flight=...)``; ``orbit`` is the other flight): the real
#: flight's block; one strip of five photos (a corridor: a road, a river, a power line); the
#: block flown with the camera pitched 35 degrees forward (oblique photos).
GRIDS: dict[str, GridSpec] = {
    "grid": GridSpec(),
    "corridor": GridSpec(strips=1, per_strip=5),
    "oblique": GridSpec(pitch_deg=35.0),
}
#: Every flight ``make_scene`` flies.
FLIGHTS: tuple[str, ...] = ("orbit", *GRIDS)
GRID = GRIDS["grid"]
# The mountain's terrain reaches about 230 m; a mapping flight keeps its height above that.
GRID_CLEARANCE = {"mountain": 230.0}


def _tilted(w2c: np.ndarray, rng: np.random.Generator, sigma_deg: float) -> np.ndarray:
    """``w2c`` with the camera turned by small random angles about its own x and y axes."""
    a, b = np.radians(rng.normal(0.0, sigma_deg, 2))
    out = w2c.copy()
    centre = -w2c[:3, :3].T @ w2c[:3, 3]
    out[:3, :3] = axis_angle([1.0, 0.0, 0.0], a) @ axis_angle([0.0, 1.0, 0.0], b) @ w2c[:3, :3]
    out[:3, 3] = -out[:3, :3] @ centre
    return out


def grid_cameras(resolution: int, heading: float, rng: np.random.Generator, spec: GridSpec = GRID,
                 ground: float = 0.0) -> tuple[list[Camera], list[Camera], dict[str, list[str]]]:
    """Photos, Track cameras and split of a mapping flight (:class:`GridSpec`) over the origin.

    ``heading`` (radians from +X) is the strips' direction; ``rng`` draws the attitude and
    position noise of the photos (the Track is noise-free); ``ground``: height added to the
    flight's (terrain). A pitched camera flies ``height x tan(pitch)`` behind its nadir position,
    so that it looks at the same ground. Photos are named ``000``, ``001``, ... in flight order
    (strip by strip, every other strip flown backwards); the split is
    :meth:`GridSpec.train_indices` for training, the other photos for testing. The Track follows
    the flight's route, N_TRACK cameras evenly spread along it.
    """
    W = H = int(resolution)
    f = spec.lens_mm / spec.sensor_mm * W
    K = np.array([[f, 0.0, W / 2.0], [0.0, f, H / 2.0], [0.0, 0.0, 1.0]])
    along = np.array([math.cos(heading), math.sin(heading), 0.0])
    across = np.array([-along[1], along[0], 0.0])
    up = np.array([0.0, 0.0, 1.0])
    da, dc = spec.spacing()
    z = spec.height + ground
    pitch = math.radians(spec.pitch_deg)
    back = -spec.height * math.tan(pitch) * along
    route = []
    for i in range(spec.strips):
        js = range(spec.per_strip) if i % 2 == 0 else reversed(range(spec.per_strip))
        for j in js:
            route.append((i - (spec.strips - 1) / 2) * dc * across + (j - (spec.per_strip - 1) / 2) * da * along
                         + back + z * up)
    route = np.array(route)
    look = -math.cos(pitch) * up + math.sin(pitch) * along

    def camera(eye: np.ndarray, name: str) -> Camera:
        return Camera(K=K, w2c=look_at(eye, eye + look, along if pitch == 0.0 else up), width=W, height=H,
                      name=name)

    views = []
    for n, eye in enumerate(route):
        cam = camera(eye + rng.normal(0.0, spec.jitter, 3) * np.array([da, dc, da]), f"{n:03d}")
        views.append(Camera(K=K, w2c=_tilted(cam.w2c, rng, spec.tilt_deg), width=W, height=H, name=cam.name))
    train = [views[i].name for i in spec.train_indices()]
    split = {"train": train, "test": [v.name for v in views if v.name not in train]}
    seg = np.linalg.norm(np.diff(route, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    at = np.linspace(0.0, s[-1], N_TRACK)
    pos = np.stack([np.interp(at, s, route[:, k]) for k in range(3)], 1)
    track = [camera(p, f"{i:03d}") for i, p in enumerate(pos)]
    return views, track, split
