"""``dibrgs export WORK --ply FILE``: the trained Gaussians as a standard 3DGS PLY.

x, y, z, normals (0), f_dc_0..2 (+ f_rest_* for the 3DGS baseline), opacity
(logit), scale_0..2 (log) and rot_0..3 (w, x, y, z), readable by common
Gaussian-splatting viewers. DIBR-GS's view-dependent neural Gaussians are decoded
once from the most central training camera.
"""
from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="export the trained Gaussians as a 3DGS PLY", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("work", type=Path, help="run folder of `dibrgs train`")
    p.add_argument("--ply", type=Path, required=True, help="output PLY file")
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (default 1: on a shared machine more threads stall on each other)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from ..evaluation.export import export_ply

    torch.set_num_threads(max(1, args.threads))

    n = export_ply(args.work, args.ply)
    print(f"wrote {n} Gaussians to {args.ply}")
    return 0
