"""``dibrgs init SCENE --out WORK``: geometry initialisation into WORK/init/.

The training views are the scene's split (``--train``/``--test``, else ``split.json``, else the
default). ``dibrgs train`` into the same folder reuses this initialisation when it trains on the
same views (same cameras and images) with the same depth prior; otherwise it initialises again.
A folder that holds a run of another scene is reported and replaced.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..common.modes import DepthMap, DepthPrior, Refine, choices
from .options import (SCENE_LAYOUTS, add_compute, add_split, apply_compute, locked, name_list, nonnegative_float,
                      positive_float)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("init", help="initial point cloud, height map and report (WORK/init/)",
                       description="SfM with the known poses, an aligned dense depth prior, overlap removal, "
                                   "voxel downsampling and the height map. Writes WORK/init/points.ply, "
                                   "height_map.npz (when it applies) and init_report.json.")
    p.add_argument("scene", type=Path, help=f"scene folder ({SCENE_LAYOUTS})")
    p.add_argument("--out", type=Path, required=True, help="work folder; outputs go to OUT/init/")
    add_split(p)
    p.add_argument("--train-ids", dest="train", type=name_list, default=argparse.SUPPRESS,
                   help=argparse.SUPPRESS)  # the earlier name of --train
    p.add_argument("--depth-prior", default="auto", choices=choices(DepthPrior),
                   help="auto = depth-anything-v2 when --depth-model is given, else mvs; gt = oracle depths")
    p.add_argument("--depth-model", default=None, help="local folder of Depth Anything V2 weights (transformers format)")
    p.add_argument("--map", dest="depth_map", default="inv", choices=choices(DepthMap),
                   help="disparity-to-depth map before alignment (inv = 1/disparity)")
    p.add_argument("--refine", default="no-ovlp", choices=choices(Refine))
    p.add_argument("--voxel", type=nonnegative_float, default=None,
                   help="voxel size in paper units (default 1.0; 0 = off)")
    p.add_argument("--scale", type=positive_float, default=None,
                   help="world units per paper unit (default: from the cameras)")
    add_compute(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..data.load import load_scene
    from ..data.split import require_train_views

    with locked(args.out, "init"):  # before torch is imported: a second writer hears at once
        apply_compute(args)
        scene = load_scene(args.scene, args.train, args.test, load_depth=args.depth_prior == "gt")
        require_train_views(scene)
        print(f"training views {', '.join(scene.train)} (split: {scene.split_source})")
        from ..geometry.config import InitConfig
        from ..geometry.pipeline import initialise
        from ..training.run_folder import replace_earlier_run

        replace_earlier_run(args.out, scene.digest(), (scene.train, scene.test), "init")
        cfg = InitConfig(depth_prior=args.depth_prior, depth_model=args.depth_model, depth_map=args.depth_map,
                         refine=args.refine, scale=args.scale)
        if args.voxel is not None:
            cfg.voxel = args.voxel
        res = initialise(scene, args.out / "init", cfg)
    print(f"{len(res.points)} points -> {args.out / 'init' / 'points.ply'}"
          + ("" if res.height_map is None else f"; height map {res.height_map.bounds.shape}")
          + f"; {res.report.values.get('init_s', 0):.1f} s")
    return 0
