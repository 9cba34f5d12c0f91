"""``dibrgs init SCENE --out WORK``: geometry initialisation into WORK/init/."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..common.modes import DepthMap, DepthPrior, Refine, choices


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("init", help="initial point cloud, height map and report (WORK/init/)",
                       description="SfM with the known poses, an aligned dense depth prior, overlap removal, "
                                   "voxel downsampling and the height map. Writes WORK/init/points.ply, "
                                   "height_map.npz (when it applies) and init_report.json.")
    p.add_argument("scene", type=Path, help="scene folder (LEVIR-NVS or COLMAP layout)")
    p.add_argument("--out", type=Path, required=True, help="work folder; outputs go to OUT/init/")
    p.add_argument("--train-ids", default=None, help="comma-separated training view ids (default: the scene's split)")
    p.add_argument("--depth-prior", default="auto", choices=choices(DepthPrior),
                   help="auto = depth-anything-v2 when --depth-model is given, else mvs; gt = oracle depths")
    p.add_argument("--depth-model", default=None, help="local folder of Depth Anything V2 weights (transformers format)")
    p.add_argument("--map", dest="depth_map", default="inv", choices=choices(DepthMap),
                   help="disparity-to-depth map before alignment (inv = 1/disparity)")
    p.add_argument("--refine", default="no-ovlp", choices=choices(Refine))
    p.add_argument("--voxel", type=float, default=None, help="voxel size in paper units (default 1.0; 0 = off)")
    p.add_argument("--scale", type=float, default=None, help="world units per paper unit (default: from the cameras)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from ..geometry.config import InitConfig
    from ..geometry.pipeline import initialise
    from ..data.load import read_any_scene

    torch.set_num_threads(min(2, torch.get_num_threads()))
    train_ids = args.train_ids.split(",") if args.train_ids else None
    scene = read_any_scene(args.scene, train_ids=train_ids, load_depth=args.depth_prior == "gt")
    import pycolmap

    pycolmap.logging.minloglevel = 1  # COLMAP progress lines would drown the decisions
    cfg = InitConfig(depth_prior=args.depth_prior, depth_model=args.depth_model, depth_map=args.depth_map,
                     refine=args.refine, scale=args.scale)
    if args.voxel is not None:
        cfg.voxel = args.voxel
    res = initialise(scene, args.out / "init", cfg)
    print(f"{len(res.points)} points -> {args.out / 'init' / 'points.ply'}"
          + ("" if res.height_map is None else f"; height map {res.height_map.bounds.shape}")
          + f"; {res.report.values.get('init_s', 0):.1f} s")
    return 0
