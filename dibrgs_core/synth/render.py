"""The Blender side of scene generation: meshes, lights, Cycles settings, cameras, and rendering
colour and exact z-depth (bpy is passed in by :func:`~.writer.make_scene`)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..camera.blender import to_blender
from ..camera.pinhole import Camera
from .layout import MeshData, city_parts, merge, mountain_parts, stadium_parts, village_parts
from .materials import Nodes, enable_nodes, mat_ground, mat_objects, mat_terrain


def add_mesh(bpy, name: str, md: MeshData, mat) -> None:
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


def build_scene(bpy, kind: str, resolution: int, rng: np.random.Generator, samples: int) -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    offset = rng.uniform(-1000, 1000, 3)
    if kind == "mountain":
        for md in mountain_parts(rng, resolution):
            add_mesh(bpy, "terrain", md, mat_terrain(bpy, offset))
    else:
        parts = {"city": city_parts, "village": village_parts, "stadium": stadium_parts}[kind](rng)
        add_mesh(bpy, "objects", merge(parts), mat_objects(bpy, offset, windows=kind == "city"))
    if kind != "mountain":
        # Flat ground, large enough to fill every orbit view (no sky visible).
        g = np.array([[-1500, -1500, 0], [1500, -1500, 0], [1500, 1500, 0], [-1500, 1500, 0.0]])
        c = np.full((4, 3), 0.5)
        add_mesh(bpy, "ground", MeshData(g, [[0, 1, 2, 3]], c, c), mat_ground(bpy, offset, kind))
    else:
        g = np.array([[-1500, -1500, 0], [1500, -1500, 0], [1500, 1500, 0], [-1500, 1500, 0.0]])
        c = np.full((4, 3), 0.5)
        add_mesh(bpy, "plain", MeshData(g, [[0, 1, 2, 3]], c, c), mat_terrain(bpy, offset))

    # Sun (fixed per seed) and a uniform sky.
    sun = bpy.data.lights.new("sun", "SUN")
    sun.energy = 3.5
    sun.angle = math.radians(1.0)
    sun_ob = bpy.data.objects.new("sun", sun)
    az, el = rng.uniform(0, 2 * np.pi), math.radians(rng.uniform(45, 65))
    sun_ob.rotation_euler = (math.pi / 2 - el, 0.0, az)
    sc.collection.objects.link(sun_ob)
    world = bpy.data.worlds.new("sky")
    enable_nodes(world)
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


def set_camera(bpy, cam: Camera, clip: tuple[float, float] = (1.0, 10000.0)) -> None:
    """Make ``cam`` the scene camera; ``clip``: Blender's clip start and end (metres)."""
    p = to_blender(cam)
    sc = bpy.context.scene
    ob = sc.camera
    d = ob.data
    d.lens, d.sensor_width, d.sensor_height, d.sensor_fit = p.lens, p.sensor_width, p.sensor_height, p.sensor_fit
    d.shift_x, d.shift_y = p.shift_x, p.shift_y
    d.clip_start, d.clip_end = clip
    sc.render.pixel_aspect_x, sc.render.pixel_aspect_y = p.pixel_aspect_x, p.pixel_aspect_y
    from mathutils import Matrix

    ob.matrix_world = Matrix([list(map(float, row)) for row in p.matrix_world])  # rows, not columns


def render_rgb(bpy, path: Path) -> np.ndarray:
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


def depth_mode(bpy) -> None:
    """Switch to rendering z-depth as emission: 1 sample through each pixel centre.

    Every surface emits its camera-space z (Camera Data "View Z Depth") and the
    world is black, so a pixel holds the exact z-depth at its centre and 0 where
    the ray hits nothing. (Blender 5.0's bpy does not write the Depth pass into
    the multilayer EXR, and that pass would be jittered by the pixel filter.)
    """
    sc = bpy.context.scene
    mat = bpy.data.materials.new("zdepth")
    g = Nodes(mat)
    cd = g.n("ShaderNodeCameraData")
    em = g.n("ShaderNodeEmission")
    em.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    g.link(cd.outputs["View Z Depth"], em.inputs["Strength"])
    out = g.n("ShaderNodeOutputMaterial")
    g.link(em.outputs[0], out.inputs["Surface"])
    sc.view_layers[0].material_override = mat
    black = bpy.data.worlds.new("black")
    enable_nodes(black)
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
