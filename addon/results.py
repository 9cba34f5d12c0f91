"""Bringing subprocess outputs into Blender: renders, metrics, decisions, init geometry, fly-through."""
from __future__ import annotations

from pathlib import Path

import bpy
from mathutils import Matrix

from . import compositor, scene_build
from ._core import camera_blender, pinhole, reports


def _image(name: str, path: Path) -> bpy.types.Image:
    """Image datablock ``name`` showing ``path`` (reloaded when it already exists)."""
    img = bpy.data.images.get(name)
    if img is not None and Path(bpy.path.abspath(img.filepath)).resolve() == path.resolve():
        img.reload()
        return img
    if img is not None:
        bpy.data.images.remove(img)
    img = bpy.data.images.load(str(path))
    img.name = name
    img.colorspace_settings.name = "sRGB"  # the renders are sRGB PNGs (see compositor.color_manage)
    return img


def load_renders(scene: bpy.types.Scene, folder: Path, stems: list[str], kind: str) -> list[str]:
    """Load ``folder/STEM.png`` as images named ``{kind}_{stem}`` and list them as the results of that kind.

    Results of the same kind that are not among ``stems`` (an earlier run's) leave the list.
    Raises FileNotFoundError naming the first missing render.
    """
    props = scene.dibrgs
    names = []
    for stem in stems:
        p = folder / f"{stem}.png"
        if not p.is_file():
            raise FileNotFoundError(f"render missing: {p}")
        name = stem if stem.startswith(kind) else f"{kind}_{stem}"
        _image(name, p)
        if name not in props.results:
            item = props.results.add()
            item.name = name
        props.results[name].kind = kind
        names.append(name)
    for item in list(props.results):
        if item.kind == kind and item.name not in names:
            props.results.remove(props.results.find(item.name))
    return names


def show_all(scene: bpy.types.Scene, selected: str | None) -> None:
    """Every listed result in the compositor; ``selected`` wired to the output and Viewer."""
    props = scene.dibrgs
    for item in list(props.results):  # drop results whose image was deleted
        if item.name not in bpy.data.images:
            props.results.remove(props.results.find(item.name))
    names = [r.name for r in props.results]
    if not names:
        return
    compositor.show(scene, names, selected)
    if selected is not None:
        props.result_view = selected


def load_metrics(scene: bpy.types.Scene, path: Path) -> dict[str, float]:
    """Summary metrics of ``metrics.json`` into the panel ({} when the file does not exist)."""
    props = scene.dibrgs
    props.metrics.clear()
    if not path.exists():
        return {}
    values = reports.summary_metrics(reports.read_json(path))
    for k, v in values.items():
        m = props.metrics.add()
        m.name, m.value = k, v
    return values


def load_decisions(scene: bpy.types.Scene, path: Path) -> int:
    """Stage decisions of a report into the panel (kept as they are when the file does not exist)."""
    if not path.exists():
        return 0
    ds = reports.decisions(reports.read_json(path))
    props = scene.dibrgs
    props.decisions.clear()
    for d in ds:
        item = props.decisions.add()
        item.stage, item.step, item.applied, item.reason = d["stage"], d["step"], d["applied"], d["reason"]
    return len(ds)


def load_init(context: bpy.types.Context, init: Path) -> int:
    """Dense points, height map and decisions of ``dibrgs init`` output; returns the point count."""
    ply = init / "points.ply"
    if not ply.is_file():
        raise FileNotFoundError(f"initialisation wrote no point cloud: {ply}")
    rep = init / "init_report.json"
    # The run's positions and Blender's are each relative to a point near the cameras when the
    # scene lies far from its files' origin (float32): the points go where the run's (0, 0, 0) is.
    run_origin = reports.scene_origin(reports.read_json(rep)) if rep.is_file() else (0.0, 0.0, 0.0)
    origin = tuple(float(a - b) for a, b in zip(run_origin, scene_build.scene_origin()))
    obj = scene_build.import_points(context, ply, origin)
    hm = init / "height_map.npz"
    if hm.is_file():  # absent when the init report decided the scene needs none
        scene_build.import_height_map(context, hm, origin)
    load_decisions(context.scene, rep)
    # The points give the scene's depth: an unedited path is drawn again as the trainer now sees
    # the trajectory (one photo a strip: also along each camera's heading); an edited one is kept.
    if not scene_build.path_edited(context):
        scene_build.create_path(context, scene_build.plan_path(scene_build.scene_description()))
    return len(obj.data.vertices)


def flythrough(context: bpy.types.Context, folder: Path, cams: list["pinhole.Camera"]) -> bpy.types.Object:
    """An animated camera that follows the path frame by frame, the renders as its background sequence."""
    scene = context.scene
    n = len(cams)
    first = folder / f"{cams[0].name}.png"
    if not first.is_file():
        raise FileNotFoundError(f"render missing: {first}")
    name = "flythrough"
    img = _image(name, first)
    img.source = "SEQUENCE"
    img["dibrgs_frames"] = n
    if scene_build.FLY_NAME in bpy.data.objects:
        scene_build.remove_object(bpy.data.objects[scene_build.FLY_NAME])
    root = scene_build.collection(scene, scene_build.ROOT_COLLECTION)
    obj = scene_build.new_camera_object(scene_build.FLY_NAME, root)
    scene_build.apply_camera(obj, cams[0])
    obj.rotation_mode = "QUATERNION"
    prev = None
    for f, cam in enumerate(cams, start=1):
        M = Matrix(camera_blender.to_blender(cam).matrix_world.tolist())
        loc, q, _ = M.decompose()
        if prev is not None and prev.dot(q) < 0:  # shortest way between consecutive frames
            q.negate()
        obj.location, obj.rotation_quaternion = loc, q
        obj.keyframe_insert("location", frame=f)
        obj.keyframe_insert("rotation_quaternion", frame=f)
        prev = q
    bg = obj.data.background_images.new()
    bg.image = img
    bg.image_user.frame_duration = n
    bg.image_user.frame_start = 1
    bg.image_user.use_auto_refresh = True
    obj.data.show_background_images = True
    scene.frame_start, scene.frame_end = 1, n
    props = scene.dibrgs
    if name not in props.results:
        props.results.add().name = name
    props.results[name].kind = "flythrough"
    show_all(scene, name)
    return obj
