"""Blender objects of the add-on: scene cameras, dense points, height map, path, fly-through.

Poses and intrinsics go through ``dibrgs_core.camera.pinhole.to_blender`` /
``from_blender`` only, so the Blender cameras reproduce the files exactly.
"""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

import bpy
import numpy as np
from mathutils import Matrix

from ._core import camera_blender, geometry, height_map, imagesize, jobs, pinhole, serialize, path as path_mod

ROOT_COLLECTION = "DIBR-GS"
TRAIN_COLLECTION = "DIBR-GS Train views"
TEST_COLLECTION = "DIBR-GS Held-out views"
OTHER_COLLECTION = "DIBR-GS Other views"
RESULT_COLLECTION = "DIBR-GS Results"
SPLIT_COLLECTIONS = {"train": TRAIN_COLLECTION, "test": TEST_COLLECTION, "other": OTHER_COLLECTION}
PATH_NAME = "DIBR-GS Pseudo path"
TARGET_NAME = "DIBR-GS Look-at target"
POINTS_NAME = "DIBR-GS Dense points"
HEIGHT_NAME = "DIBR-GS Height map"
FLY_NAME = "DIBR-GS Fly-through camera"
SCENE_TEXT = "DIBR-GS scene.json"
#: Scene property: the clip range (start, end) of cameras without a depth range, in the scene's units.
CLIP_KEY = "dibrgs_clip"
#: Custom properties of the path curve: :func:`path_fingerprint` as the add-on drew it, and the
#: kind of trajectory it was drawn along.
FINGERPRINT_KEY = "dibrgs_path_fingerprint"
TRAJECTORY_KEY = "dibrgs_trajectory"


# ---------------------------------------------------------------------------
# collections
# ---------------------------------------------------------------------------
def collection(scene: bpy.types.Scene, name: str, parent: bpy.types.Collection | None = None
               ) -> bpy.types.Collection:
    """The collection ``name`` linked under ``parent`` (the scene's root collection by default)."""
    coll = bpy.data.collections.get(name) or bpy.data.collections.new(name)
    parent = parent or scene.collection
    if coll.name not in parent.children:
        parent.children.link(coll)
    return coll


def _root(scene: bpy.types.Scene) -> bpy.types.Collection:
    return collection(scene, ROOT_COLLECTION)


def remove_object(obj: bpy.types.Object) -> None:
    data = obj.data
    bpy.data.objects.remove(obj)
    if data is not None and data.users == 0:
        for kind, coll in ((bpy.types.Camera, bpy.data.cameras), (bpy.types.Mesh, bpy.data.meshes),
                           (bpy.types.Curve, bpy.data.curves)):
            if isinstance(data, kind):
                coll.remove(data)
                break


def clear_collection(name: str) -> None:
    coll = bpy.data.collections.get(name)
    if coll is not None:
        for obj in list(coll.objects):
            remove_object(obj)


# ---------------------------------------------------------------------------
# cameras
# ---------------------------------------------------------------------------
def apply_camera(obj: bpy.types.Object, cam: "pinhole.Camera", scene: bpy.types.Scene | None = None) -> None:
    """Set ``obj``'s pose and camera data from an OpenCV camera (render size on ``scene`` if given;
    without a depth range, the imported scene's clip range, which also sizes its drawing)."""
    clip = bpy.context.scene.get(CLIP_KEY)
    p = camera_blender.to_blender(cam, clip=tuple(clip) if clip else None)
    d = obj.data
    if clip:  # drawn a tenth of the scene's distance across, as far as Blender allows (default 1)
        d.display_size = min(max(math.sqrt(clip[0] * clip[1]) / 10.0, 0.01), 1000.0)
    d.type = "PERSP"
    d.lens_unit = "MILLIMETERS"
    d.sensor_fit = p.sensor_fit
    d.sensor_width = p.sensor_width
    d.sensor_height = p.sensor_height
    d.lens = p.lens
    d.shift_x, d.shift_y = p.shift_x, p.shift_y
    d.clip_start, d.clip_end = p.clip_start, p.clip_end
    obj.matrix_world = Matrix(p.matrix_world.tolist())
    obj["dibrgs_resolution"] = (p.resolution_x, p.resolution_y)
    obj["dibrgs_pixel_aspect"] = (p.pixel_aspect_x, p.pixel_aspect_y)
    if scene is not None:
        set_render_size(scene, p)


def set_render_size(scene: bpy.types.Scene, p: "camera_blender.BlenderCameraParams") -> None:
    r = scene.render
    r.resolution_x, r.resolution_y, r.resolution_percentage = p.resolution_x, p.resolution_y, 100
    r.pixel_aspect_x, r.pixel_aspect_y = p.pixel_aspect_x, p.pixel_aspect_y


def camera_from_object(obj: bpy.types.Object, scene: bpy.types.Scene) -> "pinhole.Camera":
    """The OpenCV camera a Blender camera object renders with the scene's render settings."""
    if obj.type != "CAMERA":
        raise ValueError(f"{obj.name} is not a camera")
    d = obj.data
    if d.type != "PERSP":
        raise ValueError(f"{obj.name}: only perspective cameras can be rendered (type is {d.type})")
    r = scene.render
    scale = r.resolution_percentage / 100.0
    # A scene's view keeps its own photo's size (photos may differ); other cameras take the render size.
    w, h = obj["dibrgs_resolution"] if "dibrgs_view" in obj else (r.resolution_x, r.resolution_y)
    ax, ay = obj["dibrgs_pixel_aspect"] if "dibrgs_view" in obj else (r.pixel_aspect_x, r.pixel_aspect_y)
    p = camera_blender.BlenderCameraParams(
        matrix_world=np.array(obj.matrix_world, dtype=np.float64), lens=d.lens, sensor_width=d.sensor_width,
        sensor_height=d.sensor_height, sensor_fit=d.sensor_fit, shift_x=d.shift_x, shift_y=d.shift_y,
        resolution_x=max(1, round(w * scale)), resolution_y=max(1, round(h * scale)),
        pixel_aspect_x=ax, pixel_aspect_y=ay, clip_start=d.clip_start,
        clip_end=d.clip_end, name=obj.get("dibrgs_view", obj.name))
    return camera_blender.from_blender(p, depth_range=True)


def new_camera_object(name: str, coll: bpy.types.Collection) -> bpy.types.Object:
    obj = bpy.data.objects.new(name, bpy.data.cameras.new(name))
    coll.objects.link(obj)
    return obj


def build_scene(context: bpy.types.Context, desc: dict[str, Any]) -> dict[str, bpy.types.Object]:
    """Camera objects for every view of a scene description (``dibrgs_core.bridge.describe``).

    Replaces a previous import. Training views get their image as camera
    background; the render resolution is the scene camera's (the first training view): photos
    may differ in size, and Blender draws every camera in the render size's shape, while each
    view object keeps its own size (:func:`camera_from_object`). Returns view id -> camera object.
    """
    scene = context.scene
    scene[CLIP_KEY] = desc.get("clip") or camera_blender.DEFAULT_CLIP
    fit_viewport_clip(*scene[CLIP_KEY])
    for name in SPLIT_COLLECTIONS.values():
        clear_collection(name)
    for obj in [o for o in bpy.data.objects if "dibrgs_view" in o]:  # view cameras moved out of them
        remove_object(obj)
    root = _root(scene)
    objs: dict[str, bpy.types.Object] = {}
    for v in desc["views"]:
        cam = serialize.camera_from_dict(v["camera"], source=desc["root"])
        coll = collection(scene, SPLIT_COLLECTIONS[v["split"]], root)
        obj = new_camera_object(v["name"], coll)
        obj["dibrgs_view"] = v["name"]
        obj["dibrgs_split"] = v["split"]
        apply_camera(obj, cam)
        if v["split"] == "train" and v.get("image"):
            bg = obj.data.background_images.new()
            bg.image = view_photo(v["name"], v["image"], v.get("orientation", 1))
            bg.alpha = 1.0
            obj.data.show_background_images = True
        objs[v["name"]] = obj
    _drop_empty_split_collections()
    train = [objs[n] for n in desc["train"] if n in objs]
    scene.camera = train[0] if train else next(iter(objs.values()))
    active = next(v for v in desc["views"] if v["name"] == scene.camera["dibrgs_view"])
    set_render_size(scene, camera_blender.to_blender(serialize.camera_from_dict(active["camera"], source=desc["root"])))
    text = bpy.data.texts.get(SCENE_TEXT) or bpy.data.texts.new(SCENE_TEXT)
    text.from_string(json.dumps(desc, indent=1))
    return objs


def fit_viewport_clip(start: float, end: float) -> None:
    """Give the 3D views the clip range ``start``-``end`` where theirs would cut the scene away (its
    units are the file's: millimetres or kilometres are 1,000 x Blender's default either way)."""
    for screen in bpy.data.screens:
        for area in screen.areas:
            for space in area.spaces:
                if space.type == "VIEW_3D" and (space.clip_end < end or space.clip_start > start):
                    space.clip_start, space.clip_end = start, end


def view_photo(view: str, path: str, orientation: int) -> bpy.types.Image:
    """The photo of ``view`` as its camera sees it. Blender loads a file's stored pixels and ignores
    its EXIF orientation, which the library follows: a photo stored turned gets an upright copy,
    packed into the .blend (named after the view, whose id is unique where file names may not be:
    a rig's like-named photos; replaced on a new import)."""
    img = bpy.data.images.load(path, check_existing=True)
    if orientation == 1:
        return img
    w, h = img.size
    px = np.empty(w * h * img.channels, np.float32)  # RGBA: Blender holds every photo so
    img.pixels.foreach_get(px)
    up, w2, h2 = imagesize.upright_pixels(px, w, h, orientation)
    name = f"DIBR-GS {view} upright"
    old = bpy.data.images.get(name)
    if old is not None:
        bpy.data.images.remove(old)
    out = bpy.data.images.new(name, w2, h2, alpha=True, float_buffer=img.is_float)
    out.colorspace_settings.name = img.colorspace_settings.name  # shown as the photo would be (float: linear)
    out.pixels.foreach_set(up)
    out.pack()
    if img.users == 0:
        bpy.data.images.remove(img)
    return out


#: ``split_source`` of a description whose split the user changed by moving view cameras.
SPLIT_MOVED = "moved in Blender"


def scene_description(imported: bool = False) -> dict[str, Any]:
    """The description stored by :func:`build_scene` (ValueError if no scene was imported), with the
    split its view cameras' collections hold now, or as imported with ``imported``.

    The user chooses the split by moving view cameras: those in the Train views collection train,
    those in Held-out views are held out, and a view whose camera is elsewhere (or deleted) is left
    out. A split that differs from the imported one has ``split_source`` :data:`SPLIT_MOVED`.
    """
    text = bpy.data.texts.get(SCENE_TEXT)
    if text is None:
        raise ValueError("import a scene first")
    desc = json.loads(text.as_string())
    if imported:
        return desc
    where = _view_splits()
    train = [v["name"] for v in desc["views"] if where.get(v["name"]) == "train"]
    test = [v["name"] for v in desc["views"] if where.get(v["name"]) == "test"]
    if (train, test) == (desc["train"], desc["test"]):
        return desc
    for v in desc["views"]:
        v["split"] = "train" if v["name"] in train else "test" if v["name"] in test else "other"
    return dict(desc, train=train, test=test, split_source=SPLIT_MOVED)


def _view_splits() -> dict[str, str]:
    """View id -> "train" / "test" / "other" by the collections its camera objects are in (a view
    trains when any of its cameras, duplicates included, is in Train views)."""
    rank = {"train": 0, "test": 1, "other": 2}
    out: dict[str, str] = {}
    for obj in bpy.data.objects:
        if "dibrgs_view" in obj:
            names = {c.name for c in obj.users_collection}
            split = "train" if TRAIN_COLLECTION in names else "test" if TEST_COLLECTION in names else "other"
            k = str(obj["dibrgs_view"])
            if k not in out or rank[split] < rank[out[k]]:
                out[k] = split
    return out


def split_summary() -> str:
    """The split the view cameras hold, in a line for the panel."""
    desc = scene_description()
    n, left = len(desc["train"]), len(desc["views"]) - len(desc["train"]) - len(desc["test"])
    text = f"Split: {n} training, {len(desc['test'])} held-out" + (f", {left} left out" if left else "")
    return text + (" (moved in Blender)" if desc.get("split_source") == SPLIT_MOVED else " (as imported)")


def move_to_split(context: bpy.types.Context, train: list[str], test: list[str]) -> None:
    """Put the view cameras in the collections of a split: ``train`` in Train views, ``test`` in
    Held-out views, every other view in Other views (as :func:`scene_description` reads them)."""
    scene = context.scene
    root = _root(scene)
    for obj in [o for o in bpy.data.objects if "dibrgs_view" in o]:
        name = str(obj["dibrgs_view"])
        split = "train" if name in train else "test" if name in test else "other"
        target = collection(scene, SPLIT_COLLECTIONS[split], root)
        for coll in list(obj.users_collection):
            if coll is not target:
                coll.objects.unlink(obj)
        if target not in obj.users_collection:
            target.objects.link(obj)
    _drop_empty_split_collections()


def _drop_empty_split_collections() -> None:
    """An empty split keeps no collection."""
    for name in SPLIT_COLLECTIONS.values():
        coll = bpy.data.collections.get(name)
        if coll is not None and not coll.objects:
            bpy.data.collections.remove(coll)


def scene_origin() -> tuple[float, float, float]:
    """Where the imported scene's Blender frame has its (0, 0, 0) in the scene's files (non-zero for
    a scene far from its coordinate origin; :func:`~dibrgs_core.bridge.describe.describe_scene`);
    the origin itself before any import."""
    try:
        o = scene_description().get("origin")
    except ValueError:
        o = None
    return tuple(float(v) for v in o) if o and len(o) == 3 else (0.0, 0.0, 0.0)


def described_cameras(desc: dict[str, Any], split: str) -> list["pinhole.Camera"]:
    return [serialize.camera_from_dict(v["camera"], source=desc["root"]) for v in desc["views"]
            if v["split"] == split]


def reference_camera(desc: dict[str, Any], name: str = "") -> "pinhole.Camera":
    """The camera whose intrinsics pseudo and fly-through cameras copy (first training view by default)."""
    views = {v["name"]: v for v in desc["views"]}
    key = name if name in views else (desc["train"][0] if desc["train"] else next(iter(views)))
    return serialize.camera_from_dict(views[key]["camera"], source=desc["root"])


# ---------------------------------------------------------------------------
# pseudo-view path
# ---------------------------------------------------------------------------
def plan_path(desc: dict[str, Any]) -> "path_mod.PathPlan":
    """The pseudo-view path along the training cameras' acquisition trajectory (``path.plan_path``),
    with the scene's depth from the dense points when they were imported."""
    track = [serialize.camera_from_dict(c, source=desc["root"]) for c in desc.get("track", [])]
    train = described_cameras(desc, "train")
    return path_mod.plan_path(train, track, train + described_cameras(desc, "test"), points=dense_points())


def dense_points() -> np.ndarray | None:
    """(N, 3) world positions of the imported dense points (None before initialisation)."""
    obj = bpy.data.objects.get(POINTS_NAME)
    if obj is None or obj.type != "MESH" or not obj.data.vertices:
        return None
    co = np.empty(3 * len(obj.data.vertices), np.float64)
    obj.data.vertices.foreach_get("co", co)
    M = np.array(obj.matrix_world, np.float64)
    return co.reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]


def create_path(context: bpy.types.Context, plan: "path_mod.PathPlan", n_ctrl: int = 8) -> bpy.types.Object:
    """The path as an editable curve, set on ``scene.dibrgs``: an orbit as a cyclic Bezier circle
    plus a look-at Empty; flight lines and camera pairs as open poly splines, no Empty (cameras
    along them follow the training cameras' orientation).

    Circle handles are 'ALIGNED' with the length that makes each segment a circular arc to
    ~1e-6 of the radius for 8 points; moving a point moves its handles.
    """
    scene = context.scene
    props = scene.dibrgs
    for name in (PATH_NAME, TARGET_NAME):
        if name in bpy.data.objects:
            remove_object(bpy.data.objects[name])
    cu = bpy.data.curves.new(PATH_NAME, "CURVE")
    cu.dimensions = "3D"
    cu.resolution_u = 32
    root = _root(scene)
    if plan.orbit is not None:
        orbit = plan.orbit
        pts = path_mod.orbit_control_points(orbit, n_ctrl)
        tangent_len = 4.0 / 3.0 * math.tan(math.pi / (2 * n_ctrl)) * orbit.radius
        sp = cu.splines.new("BEZIER")
        sp.bezier_points.add(n_ctrl - 1)
        for k, bp in enumerate(sp.bezier_points):
            th = 2.0 * math.pi * k / n_ctrl
            tangent = -math.sin(th) * orbit.basis[0] + math.cos(th) * orbit.basis[1]
            bp.handle_left_type = bp.handle_right_type = "ALIGNED"
            bp.co = pts[k]
            bp.handle_left = pts[k] - tangent_len * tangent
            bp.handle_right = pts[k] + tangent_len * tangent
        sp.use_cyclic_u = True
    else:
        for line in plan.polylines:
            sp = cu.splines.new("POLY")
            sp.points.add(len(line) - 1)
            for pt, co in zip(sp.points, line):
                pt.co = (*co, 1.0)
    obj = bpy.data.objects.new(PATH_NAME, cu)
    obj[TRAJECTORY_KEY] = plan.kind
    root.objects.link(obj)
    props.path_curve = obj
    props.path_target = None
    if plan.orbit is not None:
        target = bpy.data.objects.new(TARGET_NAME, None)
        target.empty_display_type = "SPHERE"
        target.empty_display_size = max(plan.orbit.radius * 0.05, 1e-3)
        target.location = plan.orbit.target
        root.objects.link(target)
        props.path_target = target
    props.scene_up = plan.up
    context.view_layer.update()  # the new objects' world matrices
    obj[FINGERPRINT_KEY] = path_fingerprint(obj, props.path_target, props.scene_up)
    return obj


_SPLINE_TYPES = {"POLY": 0.0, "BEZIER": 1.0, "NURBS": 2.0}


def path_fingerprint(curve: bpy.types.Object, target: bpy.types.Object | None, up) -> str:
    """A digest of everything that places the path's cameras, exactly as stored (Blender keeps
    the float32 values bit for bit, also through save and reload): the curve's placement and
    resolution, every spline's type, settings, points and handles, the look-at target's position
    and the scene's up axis."""
    cu = curve.data
    vals = [float(v) for row in curve.matrix_world for v in row] + [float(cu.resolution_u), *map(float, up)]
    for sp in cu.splines:
        vals += [_SPLINE_TYPES.get(sp.type, 3.0), float(sp.use_cyclic_u), float(sp.order_u),
                 float(sp.use_endpoint_u), float(sp.use_bezier_u), float(sp.resolution_u),
                 float(len(sp.points)), float(len(sp.bezier_points))]
        for pt in sp.points:
            vals += list(pt.co)
        for bp in sp.bezier_points:
            vals += [*bp.co, *bp.handle_left, *bp.handle_right]
    if target is not None:
        vals += [1.0, *target.matrix_world.translation]
    return hashlib.sha256(np.asarray(vals, np.float64).tobytes()).hexdigest()


def path_edited(context: bpy.types.Context, update: bool = True) -> bool:
    """Whether the user changed the path (its curve, the look-at target, or which objects they
    are) since the add-on drew it. An unedited path is only a picture of the trajectory training
    samples itself (with jitter and a check that the cloud covers each pose), so training is
    not given it. ``update=False`` (panel drawing, which may not change data) skips refreshing
    the world matrices."""
    props = context.scene.dibrgs
    curve = props.path_curve
    if curve is None or FINGERPRINT_KEY not in curve:
        return True
    if update:
        context.view_layer.update()
    return curve[FINGERPRINT_KEY] != path_fingerprint(curve, props.path_target, props.scene_up)


def training_takes_path(context: bpy.types.Context, work: Path, resume: bool) -> bool:
    """Whether training in ``work`` is given the path's cameras (``--pseudo-path``): when the user
    edited the path, or when resuming a run that started with a path (one the add-on began before
    2026-11-24 always had one; an unchanged path then resumes it)."""
    return path_edited(context) or bool(resume and jobs.run_pseudo_path(work))


def curve_polylines(context: bpy.types.Context, obj: bpy.types.Object) -> tuple[list[np.ndarray], list[bool]]:
    """World-space points of each spline of the evaluated curve as it is now, and whether each
    is closed (from the evaluated mesh: a spline's vertices are consecutive and joined by edges)."""
    if obj is None or obj.type != "CURVE" or not obj.data.splines:
        raise ValueError("the pseudo-view path must be a curve object with a spline")
    cu = obj.data
    # A bevelled, extruded or offset curve evaluates to a surface: its centre line is wanted.
    shape = {k: getattr(cu, k) for k in ("bevel_depth", "extrude", "offset", "bevel_object", "taper_object")}
    flat = {"bevel_depth": 0.0, "extrude": 0.0, "offset": 0.0, "bevel_object": None, "taper_object": None}
    changed = any(shape[k] != flat[k] for k in shape)
    try:
        if changed:
            for k, v in flat.items():
                setattr(cu, k, v)
            context.view_layer.update()
        ev = obj.evaluated_get(context.evaluated_depsgraph_get())
        mesh = ev.to_mesh()
        try:
            co = np.empty(len(mesh.vertices) * 3)
            mesh.vertices.foreach_get("co", co)
            ev_idx = np.empty(len(mesh.edges) * 2, dtype=np.int64)
            mesh.edges.foreach_get("vertices", ev_idx)
        finally:
            ev.to_mesh_clear()
    finally:
        if changed:
            for k, v in shape.items():
                setattr(cu, k, v)
            context.view_layer.update()
    if len(co) == 0:
        raise ValueError(f"the curve {obj.name} evaluates to no points")
    mw = np.array(obj.matrix_world)
    pts = co.reshape(-1, 3) @ mw[:3, :3].T + mw[:3, 3]
    edges = {tuple(sorted(e)) for e in ev_idx.reshape(-1, 2).tolist()}
    polys, closed, start = [], [], 0
    for i in range(1, len(pts) + 1):
        if i == len(pts) or (i - 1, i) not in edges:
            polys.append(pts[start:i])
            closed.append(i - start > 2 and (start, i - 1) in edges)
            start = i
    return polys, closed


def path_cameras(context: bpy.types.Context, n: int, prefix: str, route: bool = False) -> list["pinhole.Camera"]:
    """``n`` cameras sampled from the path curve as it is now: looking at the target object when
    there is one, else following the training cameras' orientation. ``route``: along one
    continuous route through all its splines (``path.chain_polylines``; a fly-through), else
    spline by spline (pseudo views)."""
    props = context.scene.dibrgs
    polys, closed = curve_polylines(context, props.path_curve)
    if route and len(polys) > 1:
        polys, closed = [path_mod.chain_polylines(polys, closed)], [False]
    desc = scene_description()
    target = None if props.path_target is None else np.array(props.path_target.matrix_world.translation)
    like = reference_camera(desc, props.reference_view)
    train = described_cameras(desc, "train") or described_cameras(desc, "test")
    return path_mod.path_cameras(polys, n, target, np.array(props.scene_up), like, closed, prefix=prefix,
                                 follow=train)


# ---------------------------------------------------------------------------
# initialisation outputs
# ---------------------------------------------------------------------------
def import_points(context: bpy.types.Context, ply: Path,
                  origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> bpy.types.Object:
    """The dense point cloud as a vertex-only mesh with its colour attribute (Blender's PLY importer),
    placed at ``origin``: where the run's (0, 0, 0) lies in Blender's frame (both are relative to a
    point near the cameras for a scene far from its coordinate origin; :func:`scene_origin`)."""
    if POINTS_NAME in bpy.data.objects:
        remove_object(bpy.data.objects[POINTS_NAME])
    before = set(bpy.data.objects)
    root = _root(context.scene)
    with context.temp_override(collection=root):
        bpy.ops.wm.ply_import(filepath=str(ply))
    new = [o for o in bpy.data.objects if o not in before]
    if len(new) != 1:
        raise RuntimeError(f"importing {ply} created {len(new)} objects")
    obj = new[0]
    obj.name = obj.data.name = POINTS_NAME
    for coll in list(obj.users_collection):
        if coll != root:
            coll.objects.unlink(obj)
    if obj.name not in root.objects:
        root.objects.link(obj)
    obj.location = origin
    context.view_layer.update()  # matrix_world now includes it (dense_points reads it at once)
    return obj


def import_height_map(context: bpy.types.Context, npz: Path,
                      origin: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> bpy.types.Object:
    """The height map (``height_map.npz``) as a wireframe grid mesh: a vertex per cell at its bound,
    placed at ``origin`` as :func:`import_points`."""
    if HEIGHT_NAME in bpy.data.objects:
        remove_object(bpy.data.objects[HEIGHT_NAME])
    verts, quads = geometry.height_map_mesh(height_map.HeightMap.load(npz))
    me = bpy.data.meshes.new(HEIGHT_NAME)
    me.from_pydata(verts.tolist(), [], quads.tolist())
    me.update()
    obj = bpy.data.objects.new(HEIGHT_NAME, me)
    obj.display_type = "WIRE"
    obj.location = origin
    _root(context.scene).objects.link(obj)
    return obj
