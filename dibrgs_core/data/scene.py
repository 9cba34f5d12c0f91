"""The scene model every reader fills: views (camera, image, optional depth), a render track and
the train/test split (made by :mod:`.split`); content digests; camera validation shared by the
readers.

Cameras are :class:`~dibrgs_core.camera.pinhole.Camera` (OpenCV axes, world-to-camera);
images float32 RGB in [0, 1]; depth z-depth in world units (0 = unknown).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable, Sequence

import numpy as np

from ..camera.pinhole import Camera
from ..common.digest import Digest
from ..common.errors import InputError


#: What a view's pixels are: float32 (H, W, 3) RGB in [0, 1] and bool (H, W) valid pixels, None
#: when every pixel holds data (see :func:`~dibrgs_core.data.images.read_pixels`).
Pixels = tuple[np.ndarray, "np.ndarray | None"]


@dataclass(frozen=True)
class ImageFile:
    """A view's pixels left in their file: a scene of hundreds of photos holds only its cameras,
    and a run reads a photo when it uses it (the split's views), one at a time.

    Attributes:
        path: the photo's file (for messages).
        load: returns the view's :data:`Pixels` as the reader would have held them (oriented,
            undistorted, masked).
        digest: :func:`pixels_digest` of what ``load`` gives, taken when the scene was read (the
            reader decodes every photo once to check it, so a damaged file is found before a run
            starts); :meth:`read` checks it again, so a photo edited since is an error, never
            silently other pixels than the run's digest says.
        no_data: the share of its pixels without data (0 when all hold data).
    """

    path: Path
    load: Callable[[], Pixels]
    digest: str
    no_data: float = 0.0

    @classmethod
    def checked(cls, path: Path, load: Callable[[], Pixels]) -> tuple["ImageFile", tuple[int, int]]:
        """The image ``load`` reads from ``path``, read once now for its digest, and its (width, height)."""
        image, valid = load()
        return (cls(Path(path), load, pixels_digest(image, valid), 0.0 if valid is None else float(1.0 - valid.mean())),
                (image.shape[1], image.shape[0]))

    def read(self) -> Pixels:
        image, valid = self.load()
        if pixels_digest(image, valid) != self.digest:
            raise InputError(self.path, "changed since the scene was read; start again to use the new photo")
        return image, valid


def pixels_digest(image: np.ndarray, valid: np.ndarray | None = None) -> str:
    """Digest of an image's float32 values and of its valid pixels when some are not (the same for
    a view held in memory or in its file)."""
    d = Digest("pixels/1").array(np.asarray(image, np.float32))
    return (d if valid is None else d.array(np.asarray(valid, np.uint8))).hex()


class View:
    """One input view.

    Attributes:
        camera: the view's camera (its ``name`` is the view id, e.g. ``"001"``).
        image: float32 (H, W, 3) RGB in [0, 1] (sRGB-encoded values as stored); given as an array
            or as an :class:`ImageFile`, read from disk again at each use and not kept.
        valid: bool (H, W), False where the photo holds no data (transparent, no-data value,
            masked), or None when every pixel does; from the :class:`ImageFile` when given one.
            Those pixels are left out of training, evaluation and geometry.
        depth: optional float32 (H, W) z-depth in world units; 0 where unknown.
    """

    __slots__ = ("camera", "_image", "_valid", "depth")

    def __init__(self, camera: Camera, image: np.ndarray | ImageFile, depth: np.ndarray | None = None,
                 valid: np.ndarray | None = None) -> None:
        self.camera = camera
        self._image = image
        self._valid = None if valid is None or np.all(valid) else np.asarray(valid, bool)
        self.depth = depth

    def pixels(self) -> Pixels:
        """(image, valid) with one read of the file."""
        return self._image.read() if isinstance(self._image, ImageFile) else (self._image, self._valid)

    @property
    def no_data(self) -> float:
        """Share of the view's pixels without data, without reading its file."""
        if isinstance(self._image, ImageFile):
            return self._image.no_data
        return 0.0 if self._valid is None else float(1.0 - self._valid.mean())

    @property
    def image(self) -> np.ndarray:
        return self.pixels()[0]

    @property
    def valid(self) -> np.ndarray | None:
        return self.pixels()[1]

    @property
    def name(self) -> str:
        return self.camera.name

    def with_camera(self, camera: Camera) -> "View":
        """This view seen through ``camera`` (same pixels, read or not, and depth)."""
        return View(camera, self._image, self.depth, self._valid)

    def pixels_digest(self) -> str:
        """Digest of the view's pixels (taken when read for an :class:`ImageFile`)."""
        return self._image.digest if isinstance(self._image, ImageFile) else pixels_digest(self._image, self._valid)

    def __repr__(self) -> str:
        what = "in its file" if isinstance(self._image, ImageFile) else f"{np.shape(self._image)}"
        return f"View({self.name!r}, image {what}, depth {'yes' if self.depth is not None else 'no'})"


@dataclass
class Scene:
    """A multi-view scene with its train/test split.

    Attributes:
        root: the folder it was read from.
        views: view id -> :class:`View`, sorted by id.
        track: render-path cameras (may be empty).
        train, test: view ids of the split.
        split_source: where the split came from (``--train``/``--test``, ``split.json``, the default).
        layout: which reader read it: ``levir``, ``colmap`` or a frame layout's name
            (:data:`~.frame_layouts.FrameLayout`), so a user sees which of a folder's files was used.
        origin: (3,) float64, the point of the files' world frame the cameras (and everything
            computed from them) are expressed from: a position ``X`` here is ``X + origin`` in the
            scene's files. Zeros unless the scene lies far from its coordinate origin
            (:func:`local_origin`; :meth:`recentred`).
    """

    root: Path
    views: dict[str, View]
    track: list[Camera] = field(default_factory=list)
    train: list[str] = field(default_factory=list)
    test: list[str] = field(default_factory=list)
    split_source: str = "default"
    layout: str = "levir"
    origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def train_views(self) -> list[View]:
        return [self.views[i] for i in self.train]

    def test_views(self) -> list[View]:
        return [self.views[i] for i in self.test]

    @property
    def cameras(self) -> list[Camera]:
        """Cameras of all views, sorted by id."""
        return [v.camera for v in self.views.values()]

    def sizes(self) -> dict[tuple[int, int], list[str]]:
        """The views' ids by image size (width, height), most common size first: photos need not
        share one (two cameras, portrait and landscape photos); each view trains, renders and is
        evaluated at its own size."""
        out: dict[tuple[int, int], list[str]] = {}
        for k, v in self.views.items():
            out.setdefault((v.camera.width, v.camera.height), []).append(k)
        return dict(sorted(out.items(), key=lambda kv: -len(kv[1])))

    def digest(self) -> str:
        """Digest of the scene's content (every view's name, camera and image; not its path):
        two runs of the same digest are runs of the same scene."""
        return views_digest(self.views.values())

    def recentred(self) -> "Scene":
        """This scene with its cameras expressed from :func:`local_origin` (itself when that is
        the files' own origin); depth maps are unchanged (z-depth does not move with the frame)."""
        o, cams, track = in_local_frame({k: v.camera for k, v in self.views.items()}, self.track)
        if not o.any():
            return self
        views = {k: v.with_camera(cams[k]) for k, v in self.views.items()}
        return replace(self, views=views, track=track, origin=self.origin + o)


#: Camera centres farther from the coordinate origin than this many times their spread put a scene
#: in a frame of its own: the model and the rasterizer hold positions in float32 (about seven
#: digits), so a georeferenced model (UTM or ECEF coordinates, 1e5-1e7 times a flight's extent)
#: would be quantised by pixels (brighton_north moved 5e6 units off: 12.4 against 17.6 dB).
FAR_FROM_ORIGIN = 100.0


def _centres(cameras: Sequence[Camera]) -> tuple[np.ndarray, float]:
    """The cameras' mean centre (3,) and the RMS distance of their centres from it (world units)."""
    C = np.stack([np.asarray(c.center, np.float64) for c in cameras]) if len(cameras) else np.zeros((1, 3))
    mean = C.mean(axis=0)
    return mean, float(np.sqrt(((C - mean) ** 2).sum(axis=1).mean()))


def local_origin(cameras: Sequence[Camera]) -> np.ndarray:
    """(3,) world point to express a scene's positions from: zeros when the mean camera centre
    lies within ``FAR_FROM_ORIGIN`` times the centres' RMS spread of the origin (or the cameras
    have no spread), else that mean rounded to the spread's power of ten."""
    mean, spread = _centres(cameras)
    if not (np.isfinite(mean).all() and spread > 0 and math.isfinite(spread)) \
            or float(np.linalg.norm(mean)) <= FAR_FROM_ORIGIN * spread:
        return np.zeros(3)
    q = 10.0 ** math.floor(math.log10(spread))
    return np.round(mean / q) * q


def in_local_frame(cameras: dict[str, Camera], track: Sequence[Camera] = ()
                   ) -> tuple[np.ndarray, dict[str, Camera], list[Camera]]:
    """(:func:`local_origin` of the views' ``cameras``, those cameras and the ``track`` relative to
    it): the one rule the library's readers and the add-on's description both follow, so that
    their frames agree."""
    o = local_origin(list(cameras.values()))
    if not o.any():
        return o, dict(cameras), list(track)
    return o, {k: c.translated(-o) for k, c in cameras.items()}, [c.translated(-o) for c in track]


def origin_decision(scene: Scene) -> tuple[bool, str]:
    """Whether ``scene`` works in a frame of its own, and why (the ``recentre`` decision)."""
    o = np.asarray(scene.origin, np.float64)
    _, spread = _centres(scene.cameras)
    if o.any():
        return True, (f"the cameras lie {np.linalg.norm(o):.4g} from the files' coordinate origin, more than "
                      f"{FAR_FROM_ORIGIN:g} x their spread ({spread:.4g}): positions are kept relative to "
                      f"({o[0]:.10g}, {o[1]:.10g}, {o[2]:.10g}) so that float32 keeps their detail")
    return False, f"the cameras lie within {FAR_FROM_ORIGIN:g} x their spread of the coordinate origin"


def no_data_decision(scene: Scene) -> tuple[bool, str]:
    """Whether some of the split's photos hold pixels without data (left out of every stage), and
    which (the ``no_data`` decision); InputError when a training photo holds none at all."""
    empty = [i for i in scene.train if scene.views[i].no_data >= 1.0]
    if empty:
        which = f"training photo {empty[0]} holds" if len(empty) == 1 else f"training photos {', '.join(empty)} hold"
        raise InputError(scene.root, f"{which} no pixel of data (transparent, a no-data value or masked "
                                     "everywhere): train on others (--train)")
    parts = []
    for what, ids in (("training", scene.train), ("held-out", scene.test)):
        shares = {i: share for i in ids if (share := scene.views[i].no_data) > 0}
        if shares:
            parts.append(f"{len(shares)} of {len(ids)} {what} photos ("
                         + ", ".join(f"{k} {100 * v:.1f} %" for k, v in list(shares.items())[:6])
                         + (", ..." if len(shares) > 6 else "") + ")")
    if not parts:
        return False, "every pixel of the split's photos holds data"
    return True, (" and ".join(parts) + " hold pixels without data (transparent, a no-data value, masked): "
                  "left out of the loss, the geometry and the scores")


def views_digest(views: Iterable[View], depth: bool = False) -> str:
    """Digest of views' names, cameras (K, w2c, size) and pixels (:meth:`View.pixels_digest`), and
    of their depth maps with ``depth`` (see :mod:`dibrgs_core.common.digest`)."""
    d = Digest("views/2")
    for v in views:
        c = v.camera
        d.text(v.name).array(np.asarray(c.K, np.float64)).array(np.asarray(c.w2c, np.float64))
        d.json([int(c.width), int(c.height)]).text(v.pixels_digest())
        if depth:
            d.array(np.zeros(0, np.float32) if v.depth is None else np.asarray(v.depth, np.float32))
    return d.hex()


def validate_camera_arrays(w2c: np.ndarray, K: np.ndarray, depth_range: tuple[float, float] | None,
                           path: Path | None) -> None:
    """Raise InputError unless w2c is a finite rigid transform and K a finite upper-triangular pinhole."""
    if not (np.isfinite(w2c).all() and np.isfinite(K).all()):
        raise InputError(path, "camera has NaN or infinite values")
    if depth_range is not None and not all(map(math.isfinite, depth_range)):
        raise InputError(path, f"depth range {depth_range} is not finite")
    if not np.allclose(w2c[3], [0, 0, 0, 1], atol=1e-6):
        raise InputError(path, f"extrinsic last row must be 0 0 0 1, got {w2c[3].tolist()}")
    R = w2c[:3, :3]
    det = float(np.linalg.det(R))
    if abs(det) < 1e-6:
        raise InputError(path, f"extrinsic rotation is singular (det {det:.3g})")
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or det < 0:
        raise InputError(path, f"extrinsic rotation is not a rotation (det {det:.4g}, R R^T != I)")
    if abs(float(np.linalg.det(K))) < 1e-12 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"intrinsic matrix is singular or has non-positive focal length: {K.tolist()}")
    if not np.allclose(K[2], [0, 0, 1], atol=1e-9) or abs(K[1, 0]) > 1e-9:
        raise InputError(path, f"intrinsic matrix must be upper-triangular with last row 0 0 1: {K.tolist()}")
