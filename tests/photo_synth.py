"""Photos as users have them, for the readers' tests (the library's and the add-on's): taken through
COLMAP cameras with lens distortion, stored turned with an EXIF orientation, described by a
transforms.json."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from dibrgs_core.camera.pinhole import Camera, look_at
from dibrgs_core.data.levir import write_cams_file

W, H = 96, 64  # 3:2, like a drone photo


def pattern(w: int, h: int) -> np.ndarray:
    """A smooth, non-symmetric test image in [0, 1] (bilinear resampling keeps it within a few levels)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r = 0.5 + 0.45 * np.sin(x / 7.0) * np.cos(y / 9.0)
    g = (x / w) * 0.9 + 0.05
    b = (y / h) * 0.9 + 0.05
    return np.stack([r, g, b], -1)


def distort_photo(ideal: np.ndarray, K: np.ndarray, cam) -> np.ndarray:
    """The photo a camera with ``cam``'s distortion takes of the scene whose pinhole (``K``) image is ``ideal``:
    each distorted pixel looks along pycolmap's ray (cam_from_img) and samples ``ideal`` there."""
    from scipy.ndimage import map_coordinates

    h, w = cam.height, cam.width
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    pix = np.stack([u.ravel() + 0.5, v.ravel() + 0.5], 1)
    rays = np.nan_to_num(np.asarray(cam.cam_from_img(pix)))  # normalised (x/z, y/z); NaN where not invertible
    px = K[0, 0] * rays[:, 0] + K[0, 2] - 0.5
    py = K[1, 1] * rays[:, 1] + K[1, 2] - 0.5
    out = np.stack([map_coordinates(ideal[..., c], [py, px], order=1, mode="nearest") for c in range(3)], -1)
    return out.reshape(h, w, 3)


def write_distorted_model(root: Path, model: str, params: list[float], n: int = 3) -> tuple[np.ndarray, list]:
    """A COLMAP text model of ``n`` views sharing one distorted camera, with photos made through that
    distortion from a known pinhole image; returns (pinhole K, world-to-camera matrices)."""
    import pycolmap

    f = 80.0
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1.0]])
    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model=model, width=W, height=H, params=params, camera_id=1)
    rec.add_camera_with_trivial_rig(cam)
    photo = distort_photo(pattern(W, H), K, cam)
    (root / "images").mkdir(parents=True)
    w2cs = []
    for i in range(n):
        w2c = look_at([10.0 * i, 0.0, 100.0], [10.0 * i, 0.0, 0.0], [0, 1.0, 0])
        w2cs.append(w2c)
        img = pycolmap.Image(name=f"v{i}.png", camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(w2c[:3, :4]))
        Image.fromarray(np.round(photo * 255).astype(np.uint8)).save(root / "images" / f"v{i}.png")
    (root / "sparse" / "0").mkdir(parents=True)
    rec.write_text(str(root / "sparse" / "0"))
    return K, w2cs


def save_turned_jpeg(path: Path, upright: np.ndarray, orientation: int) -> None:
    """Store ``upright`` (float RGB in [0, 1]) as a JPEG the way a camera held on its side does: the
    pixels turned, and the EXIF orientation tag (1, 3, 6 or 8) saying how to turn them upright."""
    im = Image.fromarray(np.round(upright * 255).astype(np.uint8))
    stored = {1: im, 3: im.transpose(Image.Transpose.ROTATE_180), 6: im.transpose(Image.Transpose.ROTATE_90),
              8: im.transpose(Image.Transpose.ROTATE_270)}[orientation]
    exif = stored.getexif()
    exif[0x0112] = orientation
    stored.save(path, quality=95, exif=exif)


def write_turned_levir_scene(root: Path, orientations: list[int]) -> dict[str, np.ndarray]:
    """A LEVIR-layout scene of W x H views ``000``, ``001``, ... along a line, the photo of view i a
    JPEG stored turned with EXIF orientation ``orientations[i]``; returns each view's upright image."""
    (root / "Images").mkdir(parents=True)
    K = np.array([[80.0, 0, W / 2], [0, 80.0, H / 2], [0, 0, 1]])
    ups = {}
    for i, orientation in enumerate(orientations):
        cam = Camera(K=K, w2c=look_at([20.0 * i, 0, 100], [20.0 * i, 0, 0], [0, 1.0, 0]), width=W, height=H,
                     name=f"{i:03d}", depth_range=(50.0, 150.0))
        write_cams_file(root / "Cams" / f"{i:03d}.txt", cam)
        ups[cam.name] = np.roll(pattern(W, H), 7 * i, axis=1)
        save_turned_jpeg(root / "Images" / f"{i:03d}.jpg", ups[cam.name], orientation)
    return ups


def opengl_c2w(w2c: np.ndarray) -> list[list[float]]:
    """The transforms.json matrix of an OpenCV world-to-camera (computed here, not by the reader)."""
    c2w = np.linalg.inv(w2c)
    c2w[:3, 1:3] *= -1.0  # OpenCV's y down, z forward -> OpenGL's y up, z back
    return c2w.tolist()


def levir_as_transforms(levir: Path, out: Path, per_frame: bool = False, extra: dict | None = None) -> None:
    """The LEVIR scene ``levir`` rewritten as ``out/transforms.json`` (photos copied to out/images)."""
    from dibrgs_core.data.load import read_any_scene

    scene = read_any_scene(levir, load_depth=False)
    (out / "images").mkdir(parents=True)
    frames = []
    for vid, v in scene.views.items():
        shutil.copyfile(levir / "Images" / f"{vid}.png", out / "images" / f"{vid}.png")
        c = v.camera
        fr = {"file_path": f"images/{vid}" + ("" if per_frame else ".png"), "transform_matrix": opengl_c2w(c.w2c)}
        if per_frame:
            fr.update(fl_x=c.K[0, 0], fl_y=c.K[1, 1], cx=c.K[0, 2], cy=c.K[1, 2], w=c.width, h=c.height)
        frames.append(fr)
    c = next(iter(scene.views.values())).camera
    top = {} if per_frame else {"fl_x": c.K[0, 0], "fl_y": c.K[1, 1], "cx": c.K[0, 2], "cy": c.K[1, 2],
                                "w": c.width, "h": c.height}
    (out / "transforms.json").write_text(json.dumps({**top, **(extra or {}), "frames": frames}))


def assert_same_views(got, want) -> None:
    """Scene ``got`` (the generated scene ``want`` written in another layout) has ``want``'s views:
    the same names, cameras and pixels."""
    assert list(got.views) == list(want.views)
    for vid, v in got.views.items():
        w = want.views[vid].camera
        assert (v.camera.width, v.camera.height) == (w.width, w.height)
        np.testing.assert_allclose(v.camera.K, w.K, rtol=1e-12)
        np.testing.assert_allclose(v.camera.w2c, w.w2c, atol=1e-9)
        np.testing.assert_array_equal(v.image, want.views[vid].image)



def reads_as_levir(out: Path, levir: Path, camera_files: list[Path]):
    """Read the scene folder ``out`` (the generated scene ``levir`` written in another layout) and
    check it has ``levir``'s views, cameras, pixels and split, and that ``dibrgs render --cameras``
    takes the folder and each of ``camera_files`` with those cameras. Returns the scene."""
    from dibrgs_core.data.load import read_any_cameras, read_any_scene

    scene, want = read_any_scene(out), read_any_scene(levir, load_depth=False)
    assert_same_views(scene, want)
    assert scene.train == want.train
    for where in (out, *camera_files):
        cams = read_any_cameras(where)
        assert [c.name for c in cams] == list(scene.views)
        for c in cams:
            np.testing.assert_array_equal(c.w2c, scene.views[c.name].camera.w2c)
    return scene


def assert_projects_as_brown(frame, k: tuple, f: tuple, c: tuple) -> None:
    """The COLMAP camera ``frame`` gives (at its own size) projects points as the Brown model of
    OpenMVG and AliceVision with ``k`` = (k1, k2, k3, t1, t2), focal lengths ``f`` and principal
    point ``c`` (pixels): x' = x d_r + t2 (r^2 + 2 x^2) + 2 t1 x y, y' = y d_r + t1 (r^2 + 2 y^2) +
    2 t2 x y, so t1 is OpenCV's p1 (computed here, not by the reader)."""
    import pycolmap

    model, params = frame.camera_model(*frame.size)
    xy = np.random.default_rng(0).uniform(-0.4, 0.4, (50, 2))
    got = pycolmap.Camera(model=model, width=frame.size[0], height=frame.size[1], params=params).img_from_cam(
        np.column_stack([xy, np.ones(len(xy))]))
    k1, k2, k3, t1, t2 = k
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    dr = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * dr + t2 * (r2 + 2 * x * x) + 2 * t1 * x * y
    yd = y * dr + t1 * (r2 + 2 * y * y) + 2 * t2 * x * y
    np.testing.assert_allclose(got, np.column_stack([f[0] * xd + c[0], f[1] * yd + c[1]]), atol=1e-9)

def _xml_numbers(v) -> str:
    return " ".join(repr(float(x)) for x in np.ravel(v))


def levir_as_metashape(levir: Path, out: Path, chunk: np.ndarray | None = None, component: np.ndarray | None = None,
                       calibration: dict | None = None, unaligned: int = 0) -> None:
    """The LEVIR scene ``levir`` written as Metashape's camera export: ``out/cameras.xml`` and the
    photos in ``out/images`` (labels without extension). Cameras are given in the chunk's frame:
    ``chunk`` (and ``component``, for Metashape 2's components) are 4x4 similarities taking them to
    the world (identity when None); ``calibration`` overrides the sensor's entries (Metashape's
    names); ``unaligned`` more cameras without a transform (photos that were not aligned)."""
    from dibrgs_core.data.load import read_any_scene

    scene = read_any_scene(levir, load_depth=False)
    (out / "images").mkdir(parents=True)
    chunk = np.eye(4) if chunk is None else chunk
    to_chunk = np.linalg.inv(chunk @ (np.eye(4) if component is None else component))
    c = next(iter(scene.views.values())).camera
    calib = {"f": c.K[1, 1], "cx": c.K[0, 2] - c.width / 2, "cy": c.K[1, 2] - c.height / 2, "b1": c.K[0, 0] - c.K[1, 1],
             "k1": 0.0, **(calibration or {})}
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', '<document version="2.0.0">', '  <chunk label="Chunk 1">',
             '    <sensors next_id="1">', '      <sensor id="0" label="synth" type="frame">',
             f'        <resolution width="{c.width}" height="{c.height}"/>',
             '        <calibration type="frame" class="initial">'  # Metashape's initial guess: not read
             '<resolution width="1" height="1"/><f>1</f></calibration>',
             '        <calibration type="frame" class="adjusted">',
             f'          <resolution width="{c.width}" height="{c.height}"/>']
    lines += [f"          <{k}>{float(v)!r}</{k}>" for k, v in calib.items()]
    lines += ["        </calibration>", "      </sensor>", "    </sensors>"]
    if component is not None:
        s = np.cbrt(np.linalg.det(component[:3, :3]))
        lines += ['    <components next_id="1" active_id="0">', '      <component id="0" label="Component 1">',
                  f"        <transform><rotation>{_xml_numbers(component[:3, :3] / s)}</rotation>"
                  f"<translation>{_xml_numbers(component[:3, 3])}</translation><scale>{s!r}</scale></transform>",
                  "      </component>", "    </components>"]
    lines.append('    <cameras next_id="99" next_group_id="1">')
    lines.append('      <group id="0" label="flight">')  # a camera group: cameras nest one level deeper
    for k, (vid, v) in enumerate(scene.views.items()):
        shutil.copyfile(levir / "Images" / f"{vid}.png", out / "images" / f"{vid}.png")
        m = to_chunk @ np.linalg.inv(v.camera.w2c)
        comp = ' component_id="0"' if component is not None else ""
        lines.append(f'        <camera id="{k}" sensor_id="0"{comp} label="{vid}"><transform>{_xml_numbers(m)}'
                     "</transform><orientation>1</orientation></camera>")
    lines.append("      </group>")
    for k in range(unaligned):
        lines.append(f'      <camera id="{50 + k}" sensor_id="0" label="dropped{k}"/>')
    lines.append('      <camera id="60" sensor_id="0" label="unchecked" enabled="false"><transform>'
                 f'{_xml_numbers(np.eye(4))}</transform></camera>')  # disabled by the user: no photo needed
    lines.append("    </cameras>")
    s = np.cbrt(np.linalg.det(chunk[:3, :3]))
    lines += [f"    <transform><rotation locked=\"true\">{_xml_numbers(chunk[:3, :3] / s)}</rotation>"
              f"<translation locked=\"true\">{_xml_numbers(chunk[:3, 3])}</translation>"
              f"<scale locked=\"true\">{s!r}</scale></transform>", "  </chunk>", "</document>"]
    (out / "cameras.xml").write_text("\n".join(lines) + "\n")


def levir_as_opensfm(levir: Path, out: Path, camera: dict | None = None, odm: bool = True) -> None:
    """The LEVIR scene ``levir`` written as OpenSfM leaves it: ``reconstruction.json`` (in
    ``out/opensfm/`` as OpenDroneMap's project has it, else in ``out``) and the photos in
    ``out/images``; ``camera`` overrides the camera's entries (OpenSfM's names, normalised by the
    larger side; a ``brown`` camera unless it gives another ``projection_type``)."""
    from scipy.spatial.transform import Rotation

    from dibrgs_core.data.load import read_any_scene

    scene = read_any_scene(levir, load_depth=False)
    (out / "images").mkdir(parents=True)
    c = next(iter(scene.views.values())).camera
    size = max(c.width, c.height)
    cam = {"projection_type": "brown", "width": c.width, "height": c.height, "focal_x": c.K[0, 0] / size,
           "focal_y": c.K[1, 1] / size, "c_x": (c.K[0, 2] - c.width / 2) / size,
           "c_y": (c.K[1, 2] - c.height / 2) / size, "k1": 0.0, "k2": 0.0, "k3": 0.0, "p1": 0.0, "p2": 0.0,
           **(camera or {})}
    shots = {}
    for vid, v in scene.views.items():
        shutil.copyfile(levir / "Images" / f"{vid}.png", out / "images" / f"{vid}.png")
        rotvec = Rotation.from_matrix(v.camera.w2c[:3, :3]).as_rotvec()
        shots[f"{vid}.png"] = {"rotation": rotvec.tolist(), "translation": v.camera.w2c[:3, 3].tolist(),
                               "camera": "v2 synth", "orientation": 1, "gps_dop": 5.0}
    recs = [{"cameras": {"v2 synth": cam}, "shots": shots, "points": {}},
            {"cameras": {"v2 synth": cam}, "shots": dict(list(shots.items())[:2]), "points": {}}]
    folder = out / "opensfm" if odm else out
    folder.mkdir(exist_ok=True)
    (folder / "reconstruction.json").write_text(json.dumps(recs))


def levir_as_realitycapture(levir: Path, out: Path, xcr: dict | None = None, folder: str = "images") -> None:
    """The LEVIR scene ``levir`` written as RealityCapture's registration export: each photo in
    ``out/folder`` with a ``NAME.xmp`` sidecar (world-to-camera rotation, centre, focal length for a
    36 mm frame on the longer side, principal point from the centre in units of that side); ``xcr``
    overrides the sidecars' attributes (RealityCapture's names)."""
    from dibrgs_core.data.load import read_any_scene

    scene = read_any_scene(levir, load_depth=False)
    (out / folder).mkdir(parents=True, exist_ok=True)
    for vid, v in scene.views.items():
        shutil.copyfile(levir / "Images" / f"{vid}.png", out / folder / f"{vid}.png")
        c = v.camera
        side = max(c.width, c.height)
        R, C = c.w2c[:3, :3], -c.w2c[:3, :3].T @ c.w2c[:3, 3]
        attrs = {"Version": "3", "PosePrior": "locked", "Coordinates": "absolute", "DistortionModel": "brown3",
                 "FocalLength35mm": repr(c.K[0, 0] / side * 36.0), "Skew": "0", "AspectRatio": "1",
                 "PrincipalPointU": repr((c.K[0, 2] - c.width / 2) / side),
                 "PrincipalPointV": repr((c.K[1, 2] - c.height / 2) / side), **(xcr or {})}
        coeffs = attrs.pop("DistortionCoeficients", "0 0 0 0 0 0")
        (out / folder / f"{vid}.xmp").write_text(
            '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
            '  <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
            '    <rdf:Description xmlns:xcr="http://www.capturingreality.com/ns/xcr/1.1#" '
            + " ".join(f'xcr:{k}="{val}"' for k, val in attrs.items()) + ">\n"
            f"      <xcr:Rotation>{_xml_numbers(R)}</xcr:Rotation>\n"
            f"      <xcr:Position>{_xml_numbers(C)}</xcr:Position>\n"
            f"      <xcr:DistortionCoeficients>{coeffs}</xcr:DistortionCoeficients>\n"
            "    </rdf:Description>\n  </rdf:RDF>\n</x:xmpmeta>\n")


def levir_as_bundler(levir: Path, out: Path, k: tuple[float, float] = (0.0, 0.0), unregistered: int = 0) -> None:
    """The LEVIR scene ``levir`` (square pixels, principal point at the image centre) written in
    Bundler's format: ``out/bundle.out`` (OpenGL camera axes, P = R X + t; radial ``k``), the image
    list ``out/list.txt`` and the photos in ``out/images``; ``unregistered`` more cameras of f = 0
    listed with photos that do not exist."""
    from dibrgs_core.data.load import read_any_scene

    scene = read_any_scene(levir, load_depth=False)
    (out / "images").mkdir(parents=True)
    flip = np.diag([1.0, -1.0, -1.0])
    cams, names = [], []
    for vid, v in scene.views.items():
        shutil.copyfile(levir / "Images" / f"{vid}.png", out / "images" / f"{vid}.png")
        c = v.camera
        assert abs(c.K[0, 0] - c.K[1, 1]) < 1e-9 and abs(c.K[0, 2] - c.width / 2) < 1e-9
        cams.append(f"{c.K[0, 0]!r} {k[0]!r} {k[1]!r}\n" + "\n".join(_xml_numbers(r) for r in flip @ c.w2c[:3, :3])
                    + "\n" + _xml_numbers(flip @ c.w2c[:3, 3]))
        names.append(f"images/{vid}.png 0 {c.K[0, 0]!r}")
    for j in range(unregistered):
        cams.append("0 0 0\n0 0 0\n0 0 0\n0 0 0\n0 0 0")
        names.append(f"images/lost{j}.png")
    (out / "bundle.out").write_text(f"# Bundle file v0.3\n{len(cams)} 0\n" + "\n".join(cams) + "\n")
    (out / "list.txt").write_text("\n".join(names) + "\n")


def sfm_intrinsic(version: tuple[int, int, int], w: int, h: int, fx: float, fy: float, cx: float, cy: float,
                  distortion: str = "none", params: tuple = (), sensor_width: float = 36.0) -> dict:
    """An AliceVision intrinsic as file ``version`` stores it (every value a string, as AliceVision's
    JSON writer leaves it): the focal length in pixels before 1.2.2, else in mm over the sensor width
    with ``pixelRatio`` as that version reads it; the principal point from the top-left corner
    before 1.2.1, else from the centre; one ``type`` string before 1.2.8."""
    s = lambda v: repr(float(v))  # noqa: E731
    out = {"intrinsicId": "7", "width": str(w), "height": str(h), "sensorWidth": s(sensor_width),
           "sensorHeight": "24", "serialNumber": "synth", "initializationMode": "unknown", "locked": "false",
           "distortionParams": [s(p) for p in params] if params else ""}
    pp = (cx, cy) if version < (1, 2, 1) else (cx - w / 2, cy - h / 2)
    out["principalPoint"] = [s(pp[0]), s(pp[1])]
    mm = sensor_width / w  # millimetres a pixel
    if version < (1, 2, 0):
        assert fx == fy
        out["pxFocalLength"] = s(fx)
    elif version < (1, 2, 2):
        out["pxFocalLength"] = [s(fx), s(fy)]
    elif version < (1, 2, 5):
        out.update(focalLength=s(fx * mm), pixelRatio=s(fx / fy))
    elif version < (1, 2, 11):
        out.update(focalLength=s(fx * mm), pixelRatio=s(fy / fx))
    else:
        out.update(focalLength=s(fy * mm), pixelRatio=s(fy / fx))
    if version < (1, 2, 8):
        out["type"] = {"none": "pinhole", "radialk1": "radial1", "radialk3": "radial3"}.get(distortion, distortion)
    else:
        out.update(type="pinhole", distortionType=distortion, undistortionType="none")
    return out


def sfm_pose(w2c: np.ndarray) -> dict:
    """An AliceVision pose of a world-to-camera 4x4: rotation stored column-major, centre."""
    R = w2c[:3, :3]
    return {"rotation": [repr(float(v)) for v in R.T.ravel()],
            "center": [repr(float(v)) for v in -R.T @ w2c[:3, 3]]}


def levir_as_meshroom(levir: Path, out: Path, version: tuple[int, int, int] = (1, 2, 11),
                      photos: Path | None = None, intrinsic: dict | None = None, unposed: int = 0) -> Path:
    """The LEVIR scene ``levir`` written as a Meshroom project in ``out``: the StructureFromMotion
    node's ``MeshroomCache/StructureFromMotion/<id>/cameras.sfm`` (file ``version``) whose views name
    the photos by absolute path, copied to ``photos`` (default ``out/images``); ``intrinsic``
    overrides the intrinsic's entries; the last ``unposed`` views get no pose. Returns the file."""
    from dibrgs_core.data.load import read_any_scene

    scene = read_any_scene(levir, load_depth=False)
    photos = photos or out / "images"
    photos.mkdir(parents=True, exist_ok=True)
    c = next(iter(scene.views.values())).camera
    intr = {**sfm_intrinsic(version, c.width, c.height, c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]),
            **(intrinsic or {})}
    views, poses = [], []
    for k, (vid, v) in enumerate(scene.views.items()):
        shutil.copyfile(levir / "Images" / f"{vid}.png", photos / f"{vid}.png")
        view_id, pose_id = str(1000 + k), str(5000 + k)
        views.append({"viewId": view_id, "poseId": pose_id, "frameId": str(k), "intrinsicId": "7",
                      "path": str((photos / f"{vid}.png").resolve()), "width": str(c.width),
                      "height": str(c.height), "metadata": {"Exif:FocalLength": "4.5"}})
        if k < len(scene.views) - unposed:
            poses.append({"poseId": pose_id, "pose": {"transform": sfm_pose(v.camera.w2c), "locked": "0"}})
    data = {"version": [str(x) for x in version], "featuresFolders": [], "matchesFolders": [], "views": views,
            "intrinsics": [intr], "poses": poses}
    node = out / "MeshroomCache" / "StructureFromMotion" / "2f9c0e1d7a"
    node.mkdir(parents=True)
    (node / "cameras.sfm").write_text(json.dumps(data, indent=4))
    return node / "cameras.sfm"


def levir_as_openmvg(levir: Path, out: Path, camera: str = "pinhole_radial_k3", disto: tuple = (0.0, 0.0, 0.0),
                     photos: Path | None = None, unposed: int = 0) -> Path:
    """The LEVIR scene ``levir`` written as OpenMVG's output folder ``out``: ``matches/sfm_data.json``
    (views and intrinsics, as SfMInit_ImageListing writes it) and
    ``reconstruction_sequential/sfm_data.json`` (with the poses, as ConvertSfM_DataFormat writes the
    reconstruction), photos copied to ``photos`` (default ``out/images``) and named by ``root_path``;
    two intrinsics of model ``camera`` (distortion ``disto``), cereal naming the type on the first
    only; the last ``unposed`` views get no pose. Returns the reconstruction's file."""
    from dibrgs_core.data.load import read_any_scene

    scene = read_any_scene(levir, load_depth=False)
    photos = photos or out / "images"
    photos.mkdir(parents=True, exist_ok=True)
    c = next(iter(scene.views.values())).camera
    field = {"pinhole_radial_k1": "disto_k1", "pinhole_radial_k3": "disto_k3", "pinhole_brown_t2": "disto_t2",
             "fisheye": "fisheye"}.get(camera)
    intrinsics = []
    for key in (0, 1):
        data = {"width": c.width, "height": c.height, "focal_length": c.K[0, 0],
                "principal_point": [c.K[0, 2], c.K[1, 2]], **({field: list(disto)} if field else {})}
        value = {"polymorphic_id": 0x80000001, "polymorphic_name": camera} if key == 0 else {"polymorphic_id": 1}
        intrinsics.append({"key": key, "value": {**value, "ptr_wrapper": {"id": 0x80000100 + key, "data": data}}})
    views, extrinsics = [], []
    for k, (vid, v) in enumerate(scene.views.items()):
        shutil.copyfile(levir / "Images" / f"{vid}.png", photos / f"{vid}.png")
        views.append({"key": k, "value": {"polymorphic_id": 0x40000000, "ptr_wrapper": {"id": 0x80000001 + k, "data": {
            "local_path": "", "filename": f"{vid}.png", "width": c.width, "height": c.height, "id_view": k,
            "id_intrinsic": k % 2, "id_pose": k}}}})
        if k < len(scene.views) - unposed:
            R = v.camera.w2c[:3, :3]
            C = -R.T @ v.camera.w2c[:3, 3]
            extrinsics.append({"key": k, "value": {"rotation": R.tolist(), "center": C.tolist()}})
    base = {"sfm_data_version": "0.3", "root_path": str(photos.resolve()), "views": views, "intrinsics": intrinsics}
    for folder, poses in (("matches", []), ("reconstruction_sequential", extrinsics)):
        (out / folder).mkdir(parents=True, exist_ok=True)
        (out / folder / "sfm_data.json").write_text(json.dumps(
            {**base, "extrinsics": poses, "structure": [], "control_points": []}, indent=4))
    return out / "reconstruction_sequential" / "sfm_data.json"
