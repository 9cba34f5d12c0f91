"""Procedural aerial scenes rendered headless with Blender (bpy, Cycles on CPU), written in the
LEVIR-NVS layout with exact cameras and ground-truth depth::

    OUT/Images/NNN.png     8-bit sRGB views 000-020 (a mapping flight: 000-..., in flight order)
    OUT/Cams/NNN.txt       LEVIR cameras (w2c, K, DEPTH_MIN DEPTH_MAX)
    OUT/Depths/NNN.tiff    float32 z-depth (distance along the camera axis, metres)
    OUT/Depths/NNN.exr     the same depth as a 32-bit EXR (channel "Z")
    OUT/Track/NNN.txt      60 render-path cameras on the orbit (a mapping flight: along its route)
    OUT/split.json         a mapping flight only: its sparse-view split (GridSpec.train_indices)
    OUT/scene.json         generator settings (kind, seed, resolution, samples, flight, orbit or grid)

LEVIR-NVS images cannot be downloaded here, so the project renders its own scenes.
Scene geometry: :mod:`.layout`; flights and cameras: :mod:`.flights`; materials: :mod:`.materials`; Blender
scene set-up and rendering: :mod:`.render`. Everything is seeded: the geometry comes
from ``numpy.random.default_rng(seed)`` and Cycles uses a fixed sampling seed, so the
same seed gives the same images.
"""
from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from ..common.fileio import write_json
from .flights import DEFAULT_ORBIT, FLIGHTS, GRID_CLEARANCE, GRIDS, ORBITS, grid_cameras, scene_cameras
from .layout import KINDS
from .render import build_scene, default_samples, depth_mode, linear_to_srgb8, render_rgb, set_camera

log = logging.getLogger("dibrgs.scenegen")


def make_scene(kind: str, resolution: int, seed: int, out: str | Path, samples: int | None = None,
               orbit: str = DEFAULT_ORBIT, flight: str = "orbit", lens_factor: float = 1.0) -> Path:
    """Render a procedural aerial scene into ``out`` in LEVIR-NVS layout (see module docstring).

    Args:
        kind: ``city``, ``mountain``, ``village`` or ``stadium``.
        resolution: image width = height in pixels.
        seed: scene seed; the same seed gives the same scene and images.
        out: output folder (created).
        samples: Cycles samples per pixel (default :func:`default_samples`).
        orbit: the orbit of an ``orbit`` flight, a key of :data:`ORBITS` (``levir`` or ``wide``).
        flight: ``orbit`` (views 000-020, LEVIR-NVS's protocol) or a mapping flight, a key of
            :data:`~.flights.GRIDS` (``grid``, ``corridor``, ``oblique``), with its ``split.json``.
            The same seed gives the same scene under every flight.
        lens_factor: the flight flown this many times as far from the scene with a lens this many
            times as long (the attitude noise of a grid this many times smaller): the same ground in
            the same pixels, seen nearly orthographically at 100, as from a satellite.

    Returns the output folder. Must run in a background Blender/bpy process: it
    resets the current Blender file.
    """
    import bpy

    from ..data.levir import write_cams_file
    from ..data.images import write_depth_exr, write_depth_tiff, write_png

    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    if resolution < 8:
        raise ValueError(f"resolution must be >= 8, got {resolution}")
    if orbit not in ORBITS:
        raise ValueError(f"orbit must be one of {sorted(ORBITS)}, got {orbit!r}")
    if flight not in FLIGHTS:
        raise ValueError(f"flight must be one of {FLIGHTS}, got {flight!r}")
    if not lens_factor > 0:
        raise ValueError(f"lens_factor must be > 0, got {lens_factor}")
    k = float(lens_factor)
    spec = ORBITS[orbit]
    if k != 1.0:
        spec = replace(spec, radius=spec.radius * k, height=spec.height * k, nadir_height=spec.nadir_height * k,
                       lens_mm=spec.lens_mm * k)
    if not bpy.app.background:
        raise RuntimeError("make_scene resets the Blender file; run it in a background process")
    samples = default_samples(resolution) if samples is None else int(samples)
    out = Path(out)
    t0 = time.time()
    rng = np.random.default_rng(seed)
    phase = float(rng.uniform(0, 2 * np.pi))
    split = None
    if flight in GRIDS:
        # Its own noise stream: the scene below draws from rng exactly as for an orbit.
        grid = GRIDS[flight]
        if k != 1.0:
            grid = replace(grid, height=grid.height * k, lens_mm=grid.lens_mm * k, tilt_deg=grid.tilt_deg / k)
        views, track, split = grid_cameras(resolution, phase, np.random.default_rng([seed, 1]), grid,
                                           ground=GRID_CLEARANCE.get(kind, 0.0))
    else:
        views, track = scene_cameras(resolution, phase, spec)
    clip = (k, 10000.0 * k)  # Blender's clip range, as far out as the flight
    build_scene(bpy, kind, resolution, rng, samples)
    bpy.context.scene.render.threads_mode = "AUTO"
    log.info("built %s scene (seed %d) in %.1fs; rendering %d views at %dx%d, %d spp", kind, seed,
             time.time() - t0, len(views), resolution, resolution, samples)
    from tqdm import tqdm

    dmin_all, dmax_all = np.inf, 0.0
    with tempfile.TemporaryDirectory(prefix="dibrgs_scenegen_") as tmp:
        for cam in tqdm(views, desc=f"render {kind} {resolution}px", unit="view"):
            set_camera(bpy, cam, clip)
            rgb = render_rgb(bpy, Path(tmp) / f"{cam.name}.exr")
            write_png(out / "Images" / f"{cam.name}.png", linear_to_srgb8(rgb))
        depth_mode(bpy)
        for cam in tqdm(views, desc="render depth", unit="view"):
            set_camera(bpy, cam, clip)
            depth = render_rgb(bpy, Path(tmp) / f"{cam.name}_z.exr")[..., 0]
            depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
            valid = depth[depth > 0]
            dmin, dmax = (float(valid.min()), float(valid.max())) if valid.size else (1.0, 1000.0)
            dmin_all, dmax_all = min(dmin_all, dmin), max(dmax_all, dmax)
            cam.depth_range = (0.95 * dmin, 1.05 * dmax)
            write_depth_tiff(out / "Depths" / f"{cam.name}.tiff", depth)
            write_depth_exr(out / "Depths" / f"{cam.name}.exr", depth)
            write_cams_file(out / "Cams" / f"{cam.name}.txt", cam)
    for cam in track:
        cam.depth_range = (0.95 * dmin_all, 1.05 * dmax_all)
        write_cams_file(out / "Track" / f"{cam.name}.txt", cam)
    meta = {"generator": "dibrgs_core.synth.writer", "kind": kind, "seed": seed, "resolution": resolution,
            "samples": samples, "flight": flight, "lens_factor": k}
    if split is not None:
        write_json(out / "split.json", split)
        meta.update({"grid_heading_rad": phase, "grid": grid.__dict__,
                     "grid_ground": GRID_CLEARANCE.get(kind, 0.0)})
    else:
        meta.update({"orbit_phase_rad": phase, "orbit_name": orbit, "orbit": spec.__dict__})
    write_json(out / "scene.json", {**meta, "up": [0.0, 0.0, 1.0],
                                    "depth": "z-depth along the camera axis, metres; 0 = no surface"})
    log.info("wrote %s in %.1fs", out, time.time() - t0)
    return out
