"""``dibrgs eval WORK``: held-out PSNR / SSIM (scikit-image), LPIPS + AVGE with local weights, FPS.

The held-out views are the run's own (recorded in ``WORK/config.json`` when it trained), so a
split chosen with ``--train``/``--test`` or ``split.json`` is evaluated as trained. Writes
``WORK/metrics.json`` (strict JSON: an undefined or infinite metric is ``null`` with the reason)
and the held-out renders to ``WORK/renders/``. Without ``--lpips`` LPIPS and AVGE are reported as
unavailable (null), never estimated.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from .options import add_compute, apply_compute, locked, positive_int


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="evaluate a trained run on its held-out views", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("work", type=Path, help="run folder of `dibrgs train`")
    p.add_argument("--lpips", default=None,
                   help="local LPIPS weights (lpips package layout: full LPIPS state dict, or the linear heads "
                        "weights/v0.1/vgg.pth with --lpips-backbone)")
    p.add_argument("--lpips-backbone", default=None, help="torchvision vgg16/alexnet state dict for the heads-only file")
    p.add_argument("--scene", type=Path, default=None,
                   help="the scene folder, when it has moved since training (default: where the run found it; "
                        "its content must be the same)")
    p.add_argument("--fps-repeats", type=positive_int, default=3, help="passes over the held-out views when timing")
    add_compute(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..common.errors import InputError
    from ..common.fileio import dumps

    if not args.work.is_dir():
        raise InputError(args.work, "no trained model here (no such folder); run `dibrgs train` first"
                         if not args.work.exists() else "is a file, not a run folder")
    with locked(args.work, "eval"):  # before torch is imported: a second writer hears at once
        apply_compute(args)
        from ..evaluation.evaluate import evaluate

        m = evaluate(args.work, args.lpips, args.lpips_backbone, fps_repeats=args.fps_repeats,
                     scene_root=args.scene)
    summary = {k: m[k] for k in ("psnr", "ssim", "lpips", "avge", "fps", "views")}
    print(dumps(summary, indent=None))
    return 0
