#!/usr/bin/env python3
"""Render a procedural aerial scene in LEVIR-NVS layout (thin CLI over dibrgs_core.synth.writer).

Runs with the bpy module or inside Blender:

    python scripts/make_scene.py --kind city --resolution 512 --seed 0 --out /tmp/city
    blender -b -P scripts/make_scene.py -- --kind city --resolution 512 --seed 0 --out /tmp/city
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

# Inside Blender the repository is not installed: import dibrgs_core from the checkout.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dibrgs_core.synth.flights import DEFAULT_ORBIT, FLIGHTS, ORBITS  # noqa: E402
from dibrgs_core.synth.layout import KINDS  # noqa: E402
from dibrgs_core.synth.writer import make_scene  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    if argv is None:
        argv = sys.argv[1:]
        if "--" in argv:  # blender -b -P make_scene.py -- ARGS: Blender's own args come first
            argv = argv[argv.index("--") + 1:]
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kind", choices=KINDS, default="city")
    p.add_argument("--resolution", type=int, default=512, help="image width = height, pixels")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True, help="output scene folder")
    p.add_argument("--samples", type=int, default=None, help="Cycles samples per pixel")
    p.add_argument("--orbit", choices=sorted(ORBITS), default=DEFAULT_ORBIT,
                   help="acquisition orbit: levir (15 deg off nadir) or wide (35.5 deg, heavy occlusion)")
    p.add_argument("--flight", choices=FLIGHTS, default="orbit",
                   help="orbit (21 views, LEVIR-NVS protocol); grid (a nadir mapping flight: three strips "
                        "of three photos, split.json training on the middle photo of each strip); corridor (one "
                        "strip of five, training on every other); oblique (grid's block, camera pitched 35 deg "
                        "forward)")
    p.add_argument("--lens-factor", type=float, default=1.0,
                   help="fly this many times as far with a lens this many times as long: the same ground in "
                        "the same pixels, nearly orthographic at 100 (a satellite's view)")
    a = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        datefmt="%H:%M:%S")
    out = make_scene(a.kind, a.resolution, a.seed, a.out, samples=a.samples, orbit=a.orbit, flight=a.flight,
                     lens_factor=a.lens_factor)
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
