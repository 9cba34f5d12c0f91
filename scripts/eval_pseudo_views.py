#!/usr/bin/env python
"""How good are the DIBR pseudo views? Build them at the held-out cameras and compare with the real images.

For each depth prior (default: the weight-free ``mvs`` and the ``gt`` oracle)
the scene is initialised as training would do it, pseudo views are warped
from the training views into every held-out camera (progressive DIBR, as in
training), and PSNR is measured against the held-out image: over the pixels
the warp fills (``valid``), and over the whole image with padding. This
isolates the geometry's effect on supervision from the optimisation.

    python scripts/eval_pseudo_views.py SCENE [--priors mvs,gt] [--mvs FIELD=VALUE]
        [--surface auto|on|off] [--consistency-tol T] [--json FILE]
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def evaluate(scene_dir: Path, prior: str, work: Path, mvs: dict | None = None, surface: str = "auto",
             consistency_tol: float = 0.0) -> dict:
    """Initialise ``scene_dir`` with ``prior`` in ``work`` and score pseudo views at the held-out cameras.
    ``mvs`` overrides :class:`dibrgs_core.geometry.mvs.MvsConfig` fields; ``surface`` (auto | on | off) and
    ``consistency_tol`` are the trainer's pseudo-view options (:class:`dibrgs_core.training.config.PseudoConfig`)."""
    from dataclasses import replace

    import torch

    from dibrgs_core.geometry.config import InitConfig
    from dibrgs_core.geometry.pipeline import initialise
    from dibrgs_core.data.levir import read_scene
    from dibrgs_core.training.losses import psnr
    from dibrgs_core.training.pseudo_views import build_pseudo_views
    from dibrgs_core.geometry.surface import decide

    scene = read_scene(scene_dir)
    t0 = time.perf_counter()
    cfg = InitConfig(depth_prior=prior)
    cfg.mvs = replace(cfg.mvs, **(mvs or {}))
    res = initialise(scene, work / "init", cfg)
    t_init = time.perf_counter() - t0
    tests = scene.test_views()
    t0 = time.perf_counter()
    use_surface = decide(surface, [v.camera for v in scene.train_views()])[0]
    pvs = build_pseudo_views(scene.train_views(), res.points, len(tests), 0, work / "pseudo",
                             path=[v.camera for v in tests], surface=use_surface, consistency_tol=consistency_tol)
    t_pv = time.perf_counter() - t0
    rows = []
    for v, pv in zip(tests, pvs):
        img = torch.from_numpy(np.asarray(pv.image, np.float64))
        gt = torch.from_numpy(np.asarray(v.image, np.float64)[..., :3])
        kept = torch.from_numpy(pv.valid | pv.padded)
        rows.append({"view": v.name, "valid": float(pv.valid.mean()), "kept": float(kept.float().mean()),
                     "psnr_valid": float(psnr(img, gt, torch.from_numpy(pv.valid))) if pv.valid.any() else None,
                     "psnr_kept": float(psnr(img, gt, kept)) if bool(kept.any()) else None,
                     "psnr_all": float(psnr(img, gt))})
    valid_psnr = [r["psnr_valid"] for r in rows if r["psnr_valid"] is not None]
    kept_psnr = [r["psnr_kept"] for r in rows if r["psnr_kept"] is not None]
    return {"prior": prior, "points": int(len(res.points)), "init_s": t_init, "pseudo_s": t_pv,
            "surface": use_surface, "consistency_tol": consistency_tol,
            "valid": float(np.mean([r["valid"] for r in rows])),
            "kept": float(np.mean([r["kept"] for r in rows])),
            "psnr_valid": float(np.mean(valid_psnr)) if valid_psnr else None,
            "psnr_kept": float(np.mean(kept_psnr)) if kept_psnr else None,
            "psnr_all": float(np.mean([r["psnr_all"] for r in rows])), "views": rows}


def table(scene_dir: Path, results: list[dict]) -> str:
    lines = [f"Pseudo views at the {len(results[0]['views'])} held-out cameras of `{scene_dir.name}` "
             "(PSNR against the real held-out images):", "",
             "| Depth prior | height field | points | warped pixels | supervised pixels | PSNR warped (dB) "
             "| PSNR supervised (dB) | PSNR whole image (dB) | init s |",
             "|---|---|---|---|---|---|---|---|---|"]

    def f(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.2f}"

    for r in results:
        lines.append(f"| {r['prior']} | {'yes' if r['surface'] else 'no'} | {r['points']} | {100 * r['valid']:.1f}% | "
                     f"{100 * r['kept']:.1f}% | {f(r['psnr_valid'])} | {f(r['psnr_kept'])} | {r['psnr_all']:.2f} | "
                     f"{r['init_s']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", type=Path)
    p.add_argument("--priors", default="mvs,gt", help="comma-separated depth priors (mvs, gt, depth-anything)")
    p.add_argument("--mvs", action="append", default=[], metavar="FIELD=VALUE",
                   help="override an MvsConfig field (repeatable), e.g. --mvs sgm_paths=0")
    p.add_argument("--surface", choices=("auto", "on", "off"), default="auto",
                   help="complete depth holes in a height field (auto: for near-nadir views)")
    p.add_argument("--consistency-tol", type=float, default=0.0,
                   help="reject warped pixels two training views colour further apart than this (0 = keep all)")
    p.add_argument("--json", type=Path, default=None, help="also write the per-view figures here")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import torch

    torch.set_num_threads(1)
    mvs = {}
    for item in args.mvs:
        k, _, v = item.partition("=")
        mvs[k] = json.loads(v) if v not in ("", None) else v
    results = []
    with tempfile.TemporaryDirectory(prefix="dibrgs_pv_") as tmp:
        for prior in args.priors.split(","):
            results.append(evaluate(args.scene, prior.strip(), Path(tmp) / prior.strip(), mvs, args.surface,
                                    args.consistency_tol))
    print(table(args.scene, results))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
