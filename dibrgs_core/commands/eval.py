"""``dibrgs eval WORK``: held-out PSNR / SSIM (scikit-image), LPIPS + AVGE with local weights, FPS.

Writes ``WORK/metrics.json`` and the held-out renders to ``WORK/renders/``. Without
``--lpips`` LPIPS and AVGE are reported as unavailable (null), never estimated.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="evaluate a trained run on its held-out views", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("work", type=Path, help="run folder of `dibrgs train`")
    p.add_argument("--lpips", default=None,
                   help="local LPIPS weights (lpips package layout: full LPIPS state dict, or the linear heads "
                        "weights/v0.1/vgg.pth with --lpips-backbone)")
    p.add_argument("--lpips-backbone", default=None, help="torchvision vgg16/alexnet state dict for the heads-only file")
    p.add_argument("--fps-repeats", type=int, default=3, help="passes over the held-out views when timing")
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (default 1: on a shared machine more threads stall on each other)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from ..evaluation.evaluate import evaluate

    torch.set_num_threads(max(1, args.threads))
    m = evaluate(args.work, args.lpips, args.lpips_backbone, fps_repeats=args.fps_repeats)
    summary = {k: m[k] for k in ("psnr", "ssim", "lpips", "avge", "fps", "views")}
    print(json.dumps(summary))
    return 0
