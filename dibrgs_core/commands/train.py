"""``dibrgs train SCENE --out WORK``: train DIBR-GS (or the 3DGS baseline) on a scene.

The training and held-out views are the scene's split: ``--train`` / ``--test``, else the scene's
``split.json``, else the default (LEVIR-NVS: 001/008/015). Runs the geometry initialisation first
unless ``WORK/init`` holds one made from the same training views with the same depth prior.
Progress is shown with tqdm; ``--progress-json`` also prints one JSON object per line on stdout
(``iteration``, ``total``, ``loss``, ``eta_s``, ``elapsed_s``; finally ``{"done": true, "work": ...}``).
SIGINT / SIGTERM write a checkpoint and stop; ``--resume`` continues a stopped run to the same
result when asked with the same options (more ``--iterations`` are fine; any other change is refused
with the list of differences, or accepted with ``--force-config`` and recorded in report.json).
Without ``--resume`` an earlier run in WORK is replaced. One process writes into WORK at a time.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from ..common.modes import DepthPrior, IbrEncoder, MethodName, PresetName, Switch, choices
from ..training.config import PRESET_SUMMARY
from .options import (SCENE_LAYOUTS, add_split, add_compute, apply_compute, locked, nonnegative_float, positive_int,
                      resolution_scale, seed)

log = logging.getLogger("dibrgs.train")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train DIBR-GS or the 3DGS baseline", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", type=Path, help=f"scene folder ({SCENE_LAYOUTS})")
    p.add_argument("--out", type=Path, required=True, help="run folder (WORK)")
    p.add_argument("--preset", default="cpu", choices=choices(PresetName),
                   help="; ".join(f"{k}: {v}" for k, v in PRESET_SUMMARY.items()))
    p.add_argument("--method", default="dibrgs", choices=choices(MethodName))
    p.add_argument("--iterations", type=positive_int, default=None, help="override the preset's iteration count")
    p.add_argument("--curve-every", type=nonnegative_float, default=None, metavar="S",
                   help="training seconds between error-against-time curve points (default: the preset's, "
                        "10 for cpu, 60 for paper; 0: after every iteration); --resume may change it")
    p.add_argument("--resolution-scale", type=resolution_scale, default=None,
                   help="resize the images by this factor, in (0, 4] (default: the preset's pixel budget, "
                        "cpu: long side at most 512 px; else full resolution)")
    p.add_argument("--seed", type=seed, default=None)
    add_split(p)
    p.add_argument("--resume", action="store_true",
                   help="continue from WORK/checkpoint.pt if present: the same scene and split, and the same "
                        "options (more --iterations are fine; other changes are refused with the list)")
    p.add_argument("--force-config", action="store_true",
                   help="with --resume: accept changed options (recorded in report.json)")
    p.add_argument("--progress-json", action="store_true", help="JSON progress lines on stdout")
    p.add_argument("--pseudo-path", default=None,
                   help="cameras for pseudo views instead of poses sampled along the training cameras' trajectory "
                        "(anything `dibrgs render --cameras` takes: a LEVIR Cams file or folder, a JSON list, or a "
                        "scene's cameras in any layout; intrinsics in the scene's pixels, resized with its images); "
                        "every pose is used, and the log names those mostly of padding")
    g = p.add_argument_group("ablations")
    g.add_argument("--no-dense-init", action="store_true", help="anchors from sparse SfM points only")
    g.add_argument("--ibr", default="auto", choices=choices(IbrEncoder), help="IBR encoder")
    g.add_argument("--no-height", action="store_true", help="no height-constrained growth")
    g.add_argument("--no-pseudo", action="store_true", help="no pseudo-view supervision")
    g.add_argument("--pseudo", default=None, choices=choices(Switch),
                   help="pseudo views: auto (skip with >= 10 training views), on, off")
    g.add_argument("--pseudo-surface", default="auto", choices=choices(Switch),
                   help="fill pseudo-view depth holes from a height field of the cloud (auto: near-nadir views)")
    g.add_argument("--pseudo-views", type=positive_int, default=None, metavar="N",
                   help="pseudo views to sample along the trajectory (default: the preset's, 96 for cpu; "
                        "a --pseudo-path keeps its own cameras)")
    g.add_argument("--pseudo-consistency", type=nonnegative_float, default=None, metavar="TOL",
                   help="leave out pseudo-view pixels two training views colour more than TOL apart "
                        "(mean |RGB| in [0,1]; 0 keeps all; default 0.1)")
    g.add_argument("--depth-prior", default="auto", choices=choices(DepthPrior),
                   help="depth prior of the geometry initialisation (gt = oracle)")
    w = p.add_argument_group("local weights (nothing is downloaded)")
    w.add_argument("--dino-resnet", default=None, help="dino_resnet50_pretrain.pth")
    w.add_argument("--dino-vit", default=None, help="dino_vitbase8_pretrain.pth")
    w.add_argument("--depth-model", default=None, help="local Depth Anything V2 transformers folder")
    add_compute(p)
    p.set_defaults(func=run)


def config_from_args(args: argparse.Namespace):
    """The TrainConfig the arguments ask for."""
    from ..training.config import preset

    cfg = preset(args.preset)
    cfg.method = args.method
    if args.iterations is not None:
        cfg.iterations = args.iterations
    if args.curve_every is not None:
        cfg.curve_every_s = args.curve_every
    if args.resolution_scale is not None:
        cfg.resolution_scale = args.resolution_scale
    if args.seed is not None:
        cfg.seed = args.seed
    cfg.dense_init = not args.no_dense_init
    cfg.ibr = args.ibr
    cfg.height = "off" if args.no_height else "auto"
    cfg.pseudo.mode = "off" if args.no_pseudo else (args.pseudo or "auto")
    cfg.pseudo.surface = args.pseudo_surface
    if args.pseudo_consistency is not None:
        cfg.pseudo.consistency_tol = args.pseudo_consistency
    if args.pseudo_views is not None:
        cfg.pseudo.n_views = args.pseudo_views
    cfg.depth_prior = args.depth_prior
    cfg.dino_resnet = args.dino_resnet
    cfg.dino_vit = args.dino_vit
    cfg.pseudo_path = args.pseudo_path
    return cfg


def run(args: argparse.Namespace) -> int:
    import sys

    from ..common.errors import InputError

    if args.force_config and not args.resume:
        raise InputError(None, "--force-config only applies with --resume")
    if args.pseudo_views is not None and args.pseudo_path:
        raise InputError(None, "--pseudo-views does not apply with --pseudo-path (the path's cameras are the "
                               "pseudo views)")
    with locked(args.out, "train"):  # before torch is imported: a second writer hears at once
        apply_compute(args)
        if args.pseudo_path:
            from ..data.load import read_any_cameras

            read_any_cameras(args.pseudo_path)  # a bad path: one line now, not after the geometry stage
        from ..training.methods import TrainingFailed
        from ..training.trainer import Trainer

        cfg = config_from_args(args)
        tr = Trainer(args.scene, args.out, cfg, resume=args.resume, progress_json=args.progress_json,
                     depth_model=args.depth_model, train_ids=args.train, test_ids=args.test,
                     force_config=args.force_config)
        try:
            res = tr.run()
        except TrainingFailed as e:
            log.error("training failed: %s", e)
            print(f"dibrgs train: training failed: {e}", file=sys.stderr)
            return 3
    if res.status != "done":
        print(f"dibrgs train: stopped at iteration {res.iteration}; continue with --resume", file=sys.stderr)
        return 130
    log.info("trained %s: %d iterations in %.0f s (%s); run folder %s", tr.cfg.method, res.iteration, res.seconds,
             ", ".join(f"{k} {v}" for k, v in res.sizes.items()), res.work)
    return 0
