"""``dibrgs demo``: the whole pipeline on an embedded default scene.

Renders a procedural aerial city with the scene generator (Blender's bpy
module, Cycles on CPU), then runs the same stages a user runs by hand:
``train`` (which initialises the geometry first), ``eval`` of the held-out
views and ``render`` of the scene's 60-pose Track, each through the public
command line so the demo exercises exactly what users call.
"""
from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from ..common.modes import PresetName, SceneKind, choices
from .options import add_compute, locked, positive_int, resolution, seed

log = logging.getLogger("dibrgs.demo")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="render the embedded default scene and run the whole pipeline on it",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("runs/demo"), help="output folder (default runs/demo)")
    p.add_argument("--kind", default="city", choices=choices(SceneKind))
    p.add_argument("--resolution", type=resolution, default=128, help="image size of the generated views (>= 8)")
    p.add_argument("--seed", type=seed, default=0)
    p.add_argument("--preset", default="cpu", choices=choices(PresetName), help="training preset")
    p.add_argument("--iterations", type=positive_int, default=None, help="override the preset's iteration count")
    add_compute(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..cli import main as dibrgs
    from ..synth.writer import make_scene

    out: Path = args.out
    scene = out / "scene"
    work = out / "work"
    t0 = time.perf_counter()
    threads = ([] if args.threads is None else ["--threads", str(args.threads)]) + (
        [] if args.rasterizer is None else ["--rasterizer", args.rasterizer])
    with locked(out, "demo"):
        if (scene / "Cams").is_dir() and (scene / "Images").is_dir():
            log.info("scene already rendered at %s, reusing it", scene)
        else:
            log.info("rendering the default %s scene (%dx%d, seed %d) into %s", args.kind, args.resolution,
                     args.resolution, args.seed, scene)
            make_scene(kind=args.kind, resolution=args.resolution, seed=args.seed, out=scene)
        steps: list[list[str]] = []
        train = ["train", str(scene), "--out", str(work), "--preset", args.preset, "--resume", *threads]
        if args.iterations:
            train += ["--iterations", str(args.iterations)]
        steps.append(train)
        steps.append(["eval", str(work), *threads])
        steps.append(["render", str(work), "--cameras", str(scene / "Track"), "--out", str(out / "track"), *threads])
        for argv in steps:
            log.info("dibrgs %s", " ".join(argv))
            rc = dibrgs(argv)
            if rc:
                log.error("step 'dibrgs %s' failed with exit code %d", argv[0], rc)
                return rc
    print(f"\nDIBR-GS demo finished in {time.perf_counter() - t0:.0f} s. Wrote:")
    for rel, what in [("scene", "generated LEVIR-NVS scene (Images, Cams, Depths, Track)"),
                      ("work/init/points.ply", "dense initial point cloud"),
                      ("work/init/init_report.json", "geometry decisions"),
                      ("work/checkpoint.pt", "trained model"),
                      ("work/curve.png", "held-out PSNR/SSIM against training time"),
                      ("work/metrics.json", "held-out metrics"),
                      ("work/renders", "held-out renders"),
                      ("track", "renders along the 60-pose track")]:
        p = out / rel
        if p.exists():
            print(f"  {p}  - {what}")
    return 0
