#!/usr/bin/env python
"""Initialisation ablation like the paper's table "mapping, rescaling and refinement".

For Neg./Inv. x SfM/Fused x none/Reproject/No-ovlp. the dense fused cloud
(after refinement, before voxel downsampling) is reprojected into the
training views with a z-buffer (nearest point per pixel) and compared with
the ground-truth depth: MAE (world units) and Abs Rel over pixels where both
exist. "Fused" aligns against the plane-sweep MVS cloud instead of the
sparse SfM points.

No Depth Anything weights exist here, so the relative-disparity prior is the
ground-truth disparity 1/depth corrupted per view by a smooth random
multiplicative field (+-15 %, a few bumps across the image), Gaussian noise
(1 %) and an unknown affine transform (scale 5, shift 0.002 in disparity) —
the kind of view-inconsistent, low-frequency error a monocular network makes.

Also times ``initialise()`` with the default (mvs) prior. Writes the
markdown table into the ``## Initialisation`` section of docs/benchmarks.md
(``--md``), replacing an earlier version of that section only.

    python scripts/eval_init.py SCENE [--md docs/benchmarks.md]
"""
from __future__ import annotations

import argparse
import logging
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's dibrgs_core, not an installed one
# Spinning OpenMP threads (pycolmap's and torch's) make the sweep several times slower on a shared
# 2-core machine; must be set before torch is imported (as dibrgs_core.cli does).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def corrupted_disparity(depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Relative disparity from a depth map with a smooth, view-specific distortion (see module docstring)."""
    from scipy.ndimage import zoom

    H, W = depth.shape
    coarse = rng.normal(0.0, 1.0, (4, 4))
    field = zoom(coarse, (H / 4, W / 4), order=3)[:H, :W]
    field = field / max(np.abs(field).max(), 1e-9)
    with np.errstate(divide="ignore", invalid="ignore"):
        disp = np.where(np.isfinite(depth) & (depth > 0), 1.0 / depth, np.nan)
    disp = disp * (1.0 + 0.15 * field) * (1.0 + 0.01 * rng.normal(size=(H, W)))
    return (5.0 * disp + 0.002).astype(np.float32)


def reprojection_errors(cams, gts, points) -> tuple[float, float, float]:
    """(MAE, Abs Rel, coverage) of the z-buffered cloud against ground truth over the views."""
    from dibrgs_core.geometry.pointcloud import zbuffer

    abs_e, rel_e, cov = [], [], []
    for cam, gt in zip(cams, gts):
        d = zbuffer(cam, points)
        ok = np.isfinite(d) & np.isfinite(gt) & (gt > 0)
        abs_e.append(np.abs(d[ok] - gt[ok]))
        rel_e.append(np.abs(d[ok] - gt[ok]) / gt[ok])
        cov.append(ok.mean())
    a, r = np.concatenate(abs_e), np.concatenate(rel_e)
    return float(a.mean()) if a.size else float("nan"), float(r.mean()) if r.size else float("nan"), float(np.mean(cov))


def write_section(md: Path, body: str) -> None:
    """Replace (or append) the ``## Initialisation`` section of ``md``."""
    from dibrgs_core.common.fileio import write_text

    text = md.read_text() if md.exists() else "# Benchmarks\n"
    lines = text.splitlines(keepends=True)
    start = next((i for i, l in enumerate(lines) if l.strip() == "## Initialisation"), None)
    if start is None:
        new = text.rstrip("\n") + "\n\n" + body
    else:
        end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("## ")), len(lines))
        new = "".join(lines[:start]) + body + ("\n" + "".join(lines[end:]) if end < len(lines) else "")
    write_text(md, new)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--md", type=Path, default=None, help="markdown file whose ## Initialisation section is rewritten")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--train-ids", default=None, help="comma-separated training view ids (default: the scene's split)")
    ap.add_argument("--note", default="", help="extra line for the docs (e.g. which scene this is)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)

    import pycolmap
    import torch

    pycolmap.logging.minloglevel = 2
    torch.set_num_threads(2)
    from dibrgs_core.common.blas import single_thread_blas

    single_thread_blas()  # as the dibrgs command does
    from dibrgs_core.geometry.depth_prior import PriorMaps, compute_prior
    from dibrgs_core.geometry.fusion import backproject_views
    from dibrgs_core.geometry.config import InitConfig
    from dibrgs_core.geometry.pipeline import initialise, prior_depths, refine_cloud, run_sparse
    from dibrgs_core.geometry.scene_geometry import scene_geometry
    from dibrgs_core.data.load import read_any_scene
    from dibrgs_core.common.report import Report

    scene = read_any_scene(args.scene, train_ids=args.train_ids.split(",") if args.train_ids else None,
                           load_depth=True)
    cfg = InitConfig()
    geo = scene_geometry(scene, cfg)
    gts = [np.asarray(d, np.float64) for d in geo.gt_depths]
    if any(d is None for d in geo.gt_depths):
        print("eval_init: the scene has no ground-truth depth (Depths/)", file=sys.stderr)
        return 2

    # End-to-end timing with the default prior (mvs; no model to load).
    with tempfile.TemporaryDirectory() as tmp:
        t = time.time()
        res = initialise(scene, Path(tmp), cfg)
        init_wall = time.time() - t
    default_err = reprojection_errors(geo.cameras, gts, res.points)
    # The dense cloud before voxel downsampling, all of it and its measured part (confidence >= 0.5;
    # the rest was completed from the height field).
    dense = res.dense_points if res.dense_points is not None else res.points
    dconf = res.dense_confidence if res.dense_confidence is not None else np.ones(len(dense))
    dense_err = reprojection_errors(geo.cameras, gts, dense)
    meas_err = reprojection_errors(geo.cameras, gts, dense[dconf >= 0.5])
    print(f"default init: voxel cloud MAE {default_err[0]:.3f} AbsRel {default_err[1]:.4f} cov {default_err[2]:.3f}; "
          f"dense cloud MAE {dense_err[0]:.3f} AbsRel {dense_err[1]:.4f} cov {dense_err[2]:.3f}; measured part "
          f"MAE {meas_err[0]:.3f} AbsRel {meas_err[1]:.4f} cov {meas_err[2]:.3f}; {init_wall:.1f} s")

    rep = Report()
    sparse = run_sparse(geo, cfg, rep)
    mvs = compute_prior("mvs", geo.cameras, geo.images, None, sparse.points, geo.ref_distance, mvs_config=cfg.mvs)
    fused_pts, _, _ = backproject_views(geo.cameras, mvs.maps, geo.images)
    rng = np.random.default_rng(args.seed)
    rel = PriorMaps("disparity", [corrupted_disparity(d, rng) for d in gts])
    sources = {"SfM": sparse.points, "Fused": fused_pts[:: max(1, len(fused_pts) // 20000)]}
    rows = []
    for mp in ("neg", "inv"):
        for src_name, src in sources.items():
            depths = prior_depths(geo, cfg, src, Report(), depth_map=mp, prior=rel)
            for refine in ("none", "reproject", "no-ovlp"):
                pts = refine_cloud(geo, cfg, depths, refine, Report())[0]
                mae, absrel, cov = reprojection_errors(geo.cameras, gts, pts)
                rows.append((mp, src_name, refine, mae, absrel, cov, len(pts)))
                print(f"{mp:4s} {src_name:5s} {refine:9s} MAE {mae:.3f} AbsRel {absrel:.4f} cov {cov:.3f}")

    name = {"neg": "Neg.", "inv": "Inv.", "none": "--", "reproject": "Reproject", "no-ovlp": "No ovlp."}
    best = min(rows, key=lambda r: r[3])
    H, W = geo.cameras[0].height, geo.cameras[0].width
    out = ["## Initialisation\n", "\n",
           f"Scene: `{args.scene}` ({len(geo.cameras)} training views, {W}x{H}); "
           f"{args.note}\n" if args.note else
           f"Scene: `{args.scene}` ({len(geo.cameras)} training views, {W}x{H}).\n",
           "\n",
           f"Command: `python scripts/eval_init.py {args.scene} --md {args.md}` "
           f"({platform.machine()}, torch threads 2, {time.strftime('%Y-%m-%d')}).\n", "\n",
           "Relative-disparity prior (no Depth Anything weights here): ground-truth disparity 1/depth, "
           "corrupted per view by a smooth random multiplicative field (+-15 %), 1 % noise and an unknown "
           "affine transform (x5, +0.002). *Fused* aligns against the plane-sweep MVS cloud instead of "
           "the SfM points. Errors: the dense cloud after refinement (before voxel downsampling) "
           "z-buffered into the training views vs. ground-truth depth (MAE in scene units, Abs Rel), "
           "over pixels the cloud covers (Cov.).\n", "\n",
           "| Map | Source | Refine | MAE | Abs Rel | Cov. | Points |\n",
           "|---|---|---|---|---|---|---|\n"]
    for mp, s, rf, mae, ar, cov, n in rows:
        b = "**" if (mp, s, rf) == best[:3] else ""
        out.append(f"| {name[mp]} | {s} | {name[rf]} | {b}{mae:.3f}{b} | {b}{ar:.4f}{b} | {cov:.3f} | {n} |\n")
    v = res.report.values
    out += ["\n",
            f"Default `dibrgs init` (mvs prior, Inv., No ovlp., voxel 1.0 x scale {geo.scale:.3f}): "
            f"{len(res.points)} points, MAE {default_err[0]:.3f}, Abs Rel {default_err[1]:.4f}, "
            f"coverage {default_err[2]:.3f}; dense cloud before downsampling: MAE {dense_err[0]:.3f}, Abs Rel "
            f"{dense_err[1]:.4f}, coverage {dense_err[2]:.3f} (its measured part, confidence >= 0.5: MAE "
            f"{meas_err[0]:.3f}, Abs Rel {meas_err[1]:.4f}, coverage {meas_err[2]:.3f}); wall time {init_wall:.1f} s "
            f"(SfM {v.get('sfm_s', 0):.1f} s, MVS {v.get('prior_s', 0):.1f} s; no model to load).\n"]
    text = "".join(out)
    print(text)
    if args.md:
        write_section(args.md, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
