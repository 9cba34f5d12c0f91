#!/usr/bin/env python
"""Weight-free geometry on a real COLMAP scene, checked against its reference points (evaluation only).

Runs the geometry stage (``initialise()``, default mvs prior) on the scene's
training views resized to ``--long-side`` pixels, then z-buffers the dense
cloud (after overlap removal, before voxel downsampling) into every training
view and reports

* coverage: the share of training pixels the cloud gives a depth, split into
  matched (plane-sweep) and completed (height-field) pixels;
* the median relative depth error at the reference points: each point of
  ``reference_points.txt`` (``x y z ...`` per line, ``#`` comments) that
  projects inside a training view is compared with the cloud's depth at that
  pixel, ``|d - z| / z``;
* the wall time of the stage.

``reference_points.txt`` is read here only; the pipeline never sees it.
``--scale`` multiplies the scene's world coordinates (cameras and reference
points) to check that the figures do not depend on the units.

    python scripts/eval_geometry_real.py ../shared/data/brighton_north --long-side 476 [--json OUT.json]

The training views come from ``--train`` (comma-separated names), else the
scene's ``split.json`` (``{"train": [...]}``, names with or without extension).
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's dibrgs_core, not an installed one
# Spinning OpenMP threads (pycolmap's and torch's) make the sweep several times slower on a shared
# 2-core machine; must be set before torch is imported (as dibrgs_core.cli does).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def read_reference_points(path: str | Path) -> np.ndarray:
    """(N,3) float64 world points: the first three columns of a whitespace table (``#`` comments)."""
    rows = []
    for line in Path(path).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            rows.append([float(v) for v in line.split()[:3]])
    if not rows:
        raise ValueError(f"{path}: no points")
    return np.asarray(rows, np.float64)


def split_train_names(root: Path) -> list[str] | None:
    """Training view ids from ``ROOT/split.json`` (extensions dropped), or None without one."""
    p = Path(root) / "split.json"
    if not p.is_file():
        return None
    names = json.loads(p.read_text()).get("train")
    if not names:
        raise ValueError(f"{p}: no 'train' list")
    return [Path(n).stem for n in names]


def resized_scene(scene, long_side: int | None, scale: float = 1.0):
    """The scene with every view resized to ``long_side`` pixels (area average) and world units x ``scale``."""
    import torch
    import torch.nn.functional as F

    from dibrgs_core.data.scene import Scene, View

    views = {}
    for k, v in scene.views.items():
        cam, img, dep = v.camera, np.asarray(v.image, np.float32), v.depth
        if long_side and max(cam.width, cam.height) != long_side:
            cam = cam.scaled(long_side / max(cam.width, cam.height))
            t = torch.from_numpy(img).permute(2, 0, 1)[None]
            img = F.interpolate(t, size=(cam.height, cam.width), mode="area")[0].permute(1, 2, 0).numpy()
            dep = None  # no depth resampling needed here
        if scale != 1.0:
            w2c = cam.w2c.copy()
            w2c[:3, 3] *= scale
            dr = None if cam.depth_range is None else (cam.depth_range[0] * scale, cam.depth_range[1] * scale)
            cam = replace(cam, w2c=w2c, depth_range=dr)
            dep = None if dep is None else dep * scale
        views[k] = View(camera=cam, image=img, depth=dep)
    return Scene(root=scene.root, views=views, track=[], train=list(scene.train), test=list(scene.test))


def nearest_point_index(cam, points: np.ndarray) -> np.ndarray:
    """(H,W) index of the nearest point landing in each pixel of ``cam`` (-1 where none): a z-buffer."""
    H, W = cam.height, cam.width
    uv, z = cam.project(points)
    u = np.floor(uv[:, 0]).astype(np.int64)
    v = np.floor(uv[:, 1]).astype(np.int64)
    ok = np.flatnonzero((z > 0) & np.isfinite(z) & (u >= 0) & (u < W) & (v >= 0) & (v < H))
    out = np.full(H * W, -1, np.int64)
    if len(ok) == 0:
        return out.reshape(H, W)
    pix = v[ok] * W + u[ok]
    order = np.lexsort((z[ok], pix))
    pix, idx = pix[order], ok[order]
    first = np.r_[True, pix[1:] != pix[:-1]]
    out[pix[first]] = idx[first]
    return out.reshape(H, W)


def evaluate_cloud(cams, points: np.ndarray, confidence: np.ndarray | None, reference: np.ndarray,
                   completed_below: float = 0.5) -> dict:
    """Coverage and reference-point depth error of a cloud z-buffered into ``cams`` (see the module docstring).

    Points with ``confidence < completed_below`` count as completed (height field), the rest as matched.
    """
    conf = np.ones(len(points)) if confidence is None else np.asarray(confidence, np.float64)
    per_view, rel_all, rel_m, rel_c = [], [], [], []
    n_pix = n_cov = n_matched = 0
    for cam in cams:
        idx = nearest_point_index(cam, points)
        has = idx >= 0
        depth = np.full(idx.shape, np.nan)
        depth[has] = cam.world_to_cam(points[idx[has]])[:, 2]
        matched = np.zeros(idx.shape, bool)
        matched[has] = conf[idx[has]] >= completed_below
        uv, z = cam.project(reference)
        u = np.floor(uv[:, 0]).astype(np.int64)
        v = np.floor(uv[:, 1]).astype(np.int64)
        inside = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        u, v, z = u[inside], v[inside], z[inside]
        d = depth[v, u]
        got = np.isfinite(d)
        rel = np.abs(d[got] - z[got]) / z[got]
        m = matched[v, u][got]
        rel_all.append(rel)
        rel_m.append(rel[m])
        rel_c.append(rel[~m])
        n_pix += idx.size
        n_cov += int(has.sum())
        n_matched += int(matched.sum())
        per_view.append({"view": cam.name, "coverage": float(has.mean()), "matched": float(matched.mean()),
                         "ref_points": int(inside.sum()), "ref_with_depth": int(got.sum()),
                         "median_rel_error": float(np.median(rel)) if rel.size else float("nan")})
    cat = np.concatenate(rel_all)
    catm, catc = np.concatenate(rel_m), np.concatenate(rel_c)
    med = lambda a: float(np.median(a)) if a.size else float("nan")  # noqa: E731
    return {"coverage": n_cov / max(n_pix, 1), "matched_coverage": n_matched / max(n_pix, 1),
            "median_rel_error": med(cat), "median_rel_error_matched": med(catm),
            "median_rel_error_completed": med(catc), "p90_rel_error": float(np.percentile(cat, 90)) if cat.size else float("nan"),
            "share_rel_error_over_5pct": float((cat > 0.05).mean()) if cat.size else float("nan"),
            "ref_samples": int(cat.size), "ref_samples_matched": int(catm.size), "views": per_view}


def plot_views(path: Path, views, points: np.ndarray, confidence: np.ndarray | None, reference: np.ndarray) -> None:
    """PNG, one column per training view: the cloud's depth (z-buffer), and the photo with the completed
    pixels greyed and the reference points coloured by relative depth error (green 0 to red >= 5 %)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dibrgs_core.common.fileio import atomic_path

    conf = np.ones(len(points)) if confidence is None else np.asarray(confidence)
    n = len(views)
    aspect = views[0].camera.height / views[0].camera.width
    fig, ax = plt.subplots(2, n, figsize=(4.2 * n + 1.5, 2 * 4.2 * aspect + 0.8), squeeze=False, layout="constrained")
    depths = []
    for v in views:
        idx = nearest_point_index(v.camera, points)
        d = np.full(idx.shape, np.nan)
        d[idx >= 0] = v.camera.world_to_cam(points[idx[idx >= 0]])[:, 2]
        depths.append((idx, d))
    lo, hi = np.nanpercentile(np.concatenate([d.ravel() for _, d in depths]), [1, 99])
    for k, (v, (idx, d)) in enumerate(zip(views, depths)):
        im = ax[0, k].imshow(d, cmap="turbo", vmin=lo, vmax=hi)
        ax[0, k].set_title(f"{v.name}: cloud depth", fontsize=9)
        completed = (idx >= 0) & (conf[np.maximum(idx, 0)] < 0.5)
        ax[1, k].imshow(np.clip(v.image, 0, 1))
        ax[1, k].imshow(np.where(completed, 1.0, np.nan), cmap="gray", alpha=0.45, vmin=0, vmax=1)
        uv, z = v.camera.project(reference)
        u, w = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        ok = (z > 0) & (u >= 0) & (u < v.camera.width) & (w >= 0) & (w < v.camera.height)
        dz = d[w[ok], u[ok]]
        rel = np.abs(dz - z[ok]) / z[ok]
        sc = ax[1, k].scatter(u[ok], w[ok], c=np.nan_to_num(rel, nan=1.0), s=2, cmap="RdYlGn_r", vmin=0, vmax=0.05)
        ax[1, k].set_title("completed (grey), reference points by error", fontsize=9)
        for a in ax[:, k]:
            a.axis("off")
    fig.colorbar(im, ax=ax[0].tolist(), shrink=0.8, label="z-depth (scene units)")
    fig.colorbar(sc, ax=ax[1].tolist(), shrink=0.8, label="relative depth error")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=60)
    plt.close(fig)


def run(scene_dir: Path, train: list[str] | None, long_side: int | None, scale: float = 1.0,
        work: Path | None = None, config=None, png: Path | None = None) -> dict:
    """Geometry stage on the scene and its evaluation (a dict of figures)."""
    from dibrgs_core.data.load import read_any_scene
    from dibrgs_core.geometry.config import InitConfig
    from dibrgs_core.geometry.pipeline import initialise

    scene_dir = Path(scene_dir)
    train = train or split_train_names(scene_dir)
    if not train:
        raise ValueError(f"{scene_dir}: no training views (give --train or a split.json)")
    scene = read_any_scene(scene_dir, train_ids=train, load_depth=False)
    # in the scene's frame (its origin subtracted, as from its cameras), then its units
    reference = (read_reference_points(scene_dir / "reference_points.txt") - scene.origin) * scale
    scene = resized_scene(scene, long_side, scale)
    cfg = config or InitConfig()
    with tempfile.TemporaryDirectory() as tmp:
        t = time.time()
        res = initialise(scene, Path(work or tmp), cfg)
        wall = time.time() - t
    cams = [v.camera for v in scene.train_views()]
    out = evaluate_cloud(cams, res.dense_points, res.dense_confidence, reference)
    if png:
        plot_views(png, scene.train_views(), res.dense_points, res.dense_confidence, reference)
    v = res.report.values
    out.update(scene=str(scene_dir), train=train, size=[cams[0].width, cams[0].height], scale=scale,
               init_s=wall, sfm_s=v.get("sfm_s"), prior_s=v.get("prior_s"), completion_s=v.get("completion_s"),
               sfm_points=v.get("sfm_points"), points=len(res.points), dense_points=len(res.dense_points),
               mvs=v.get("mvs"), load=os.getloadavg()[0])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--train", default=None, help="comma-separated training view names (default: split.json)")
    ap.add_argument("--long-side", type=int, default=476, help="resize views to this long side (0 = as stored)")
    ap.add_argument("--scale", type=float, default=1.0, help="multiply world coordinates (units check)")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    ap.add_argument("--work", type=Path, default=None, help="keep the init outputs here (default: a temp folder)")
    ap.add_argument("--png", type=Path, default=None, help="write a figure of the views' depth and errors here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import pycolmap
    import torch

    pycolmap.logging.minloglevel = 2
    torch.set_num_threads(2)
    from dibrgs_core.common.blas import single_thread_blas

    single_thread_blas()  # as the dibrgs command does
    from dibrgs_core.common.fileio import write_json

    try:
        res = run(args.scene, args.train.split(",") if args.train else None, args.long_side or None, args.scale,
                  args.work, png=args.png)
    except (ValueError, OSError) as e:
        print(f"eval_geometry_real: {e}", file=sys.stderr)
        return 2
    print(f"{res['scene']} {res['size'][0]}x{res['size'][1]} train {','.join(res['train'])} (scale {res['scale']:g})")
    for pv in res["views"]:
        print(f"  {pv['view']}: coverage {100 * pv['coverage']:.1f} % (matched {100 * pv['matched']:.1f} %), "
              f"{pv['ref_with_depth']}/{pv['ref_points']} reference points with depth, "
              f"median rel. error {100 * pv['median_rel_error']:.2f} %")
    print(f"coverage {100 * res['coverage']:.1f} % (matched {100 * res['matched_coverage']:.1f} %); median relative "
          f"depth error {100 * res['median_rel_error']:.2f} % (matched {100 * res['median_rel_error_matched']:.2f} %, "
          f"completed {100 * res['median_rel_error_completed']:.2f} %; p90 {100 * res['p90_rel_error']:.1f} %, "
          f"{100 * res['share_rel_error_over_5pct']:.1f} % over 5 %) at {res['ref_samples']} reference samples")
    print(f"init {res['init_s']:.1f} s (SfM {res['sfm_s'] or 0:.1f} s, MVS {res['prior_s'] or 0:.1f} s, "
          f"completion {res['completion_s'] or 0:.1f} s); {res['points']} points after voxel downsampling; "
          f"load {res['load']:.2f}")
    if args.json:
        write_json(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
