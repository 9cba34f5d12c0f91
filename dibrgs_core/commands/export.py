"""``dibrgs export WORK --ply FILE``: the trained Gaussians as a standard 3DGS PLY.

x, y, z, normals (0), f_dc_0..2 (+ f_rest_* for the 3DGS baseline), opacity
(logit), scale_0..2 (log) and rot_0..3 (w, x, y, z), readable by common
Gaussian-splatting viewers. DIBR-GS's view-dependent neural Gaussians are decoded
once from the most central training camera. Positions are the run's: for a scene far from its
coordinate origin (``dibrgs info``'s ``origin``), relative to that origin, which the header gives
as ``comment origin X Y Z`` and the log repeats.
FILE is written atomically; a symbolic link is followed, and anything but a regular file (a
folder, a FIFO, a device) is refused.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from .options import add_compute, apply_compute


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="export the trained Gaussians as a 3DGS PLY", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("work", type=Path, help="run folder of `dibrgs train`")
    p.add_argument("--ply", type=Path, required=True, help="output PLY file")
    add_compute(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..common.fileio import resolve_target
    from ..evaluation.export import export_ply

    resolve_target(args.ply)  # refuse a folder or device before the model is read
    apply_compute(args)
    n = export_ply(args.work, args.ply)
    print(f"wrote {n} Gaussians to {args.ply}")
    return 0
