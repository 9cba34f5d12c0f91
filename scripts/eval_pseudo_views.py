#!/usr/bin/env python
"""How good are the DIBR pseudo views, and how fast? Score them against real held-out images.

For each dense cloud - made by the geometry stage with a depth prior (default: the
weight-free ``mvs`` and the ``gt`` oracle), or read from a PLY (``--points``, e.g. another
branch's ``WORK/init/points.ply``) - pseudo views are warped from the training views
(progressive DIBR, as in training):

* into every held-out camera, and compared with the held-out image: PSNR over the pixels
  the warp fills (``valid``), over the supervised pixels (warped + padded), and over the
  whole image. This isolates the geometry's effect on supervision from the optimisation;
* with ``--pseudo N``, as training builds them: N poses sampled along the training cameras'
  trajectory, filtered by cloud cover and warped share; reported: the trajectory class,
  views kept / tried, mean warped / padded / rejected shares, CPU seconds a view (one
  torch thread; process time) and wall seconds in all.

    python scripts/eval_pseudo_views.py SCENE [--priors mvs,gt] [--points PLY ...]
        [--train IDS --test IDS] [--resolution-scale S] [--pseudo N]
        [--mvs FIELD=VALUE] [--surface auto|on|off] [--consistency-tol T] [--json FILE] [--png FILE]

``--png`` draws, per cloud, the first two sampled pseudo views (``--pseudo``) beside the nearest
training photo: warped pixels as they are, padded ones tinted blue, rejected ones red.
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


def read(scene_dir: Path, train: str | None, test: str | None, scale: float):
    """Training and held-out views at ``scale`` x their resolution (images area-resized, cameras
    scaled, as the trainer's frames), and the scene at full resolution (for the geometry stage)."""
    from dibrgs_core.data.load import read_any_scene
    from dibrgs_core.data.scene import View
    from dibrgs_core.training.frames import resize_image

    ids = (lambda s: [x.strip() for x in s.split(",") if x.strip()] if s else None)
    scene = read_any_scene(scene_dir, train_ids=ids(train), test_ids=ids(test))

    def at_scale(v):
        if scale == 1.0:
            return v
        return View(v.camera.scaled(scale), resize_image(np.clip(np.nan_to_num(v.image), 0, 1), scale)[..., :3])

    return scene, [at_scale(v) for v in scene.train_views()], [at_scale(v) for v in scene.test_views()]


def cloud(scene, prior: str, work: Path, mvs: dict | None) -> tuple[np.ndarray, float]:
    """The geometry stage's dense cloud with ``prior`` (``MvsConfig`` overrides in ``mvs``) and its seconds."""
    from dataclasses import replace

    from dibrgs_core.geometry.config import InitConfig
    from dibrgs_core.geometry.pipeline import initialise

    t0 = time.perf_counter()
    cfg = InitConfig(depth_prior=prior)
    cfg.mvs = replace(cfg.mvs, **(mvs or {}))
    res = initialise(scene, work / "init", cfg)
    # float32-rounded, as training reads it (setup.build_dibrgs)
    return np.asarray(res.points, np.float32).astype(np.float64), time.perf_counter() - t0


def evaluate(label: str, points: np.ndarray, train_views: list, tests: list, work: Path, surface: str = "auto",
             consistency_tol: float = 0.0, pseudo: int = 0, seed: int = 0, init_s: float = 0.0) -> dict:
    """Score pseudo views of ``points`` at the held-out cameras; with ``pseudo`` > 0 also build that many
    trajectory-sampled views as training does and time them."""
    import torch

    from dibrgs_core.geometry.surface import decide
    from dibrgs_core.training.losses import psnr
    from dibrgs_core.training.pseudo_views import build_pseudo_views

    use_surface = decide(surface, [v.camera for v in train_views])[0]
    t0 = time.perf_counter()
    held = build_pseudo_views(train_views, points, len(tests), 0, work / "pseudo_test",
                              path=[v.camera for v in tests], surface=use_surface, consistency_tol=consistency_tol)
    t_pv = time.perf_counter() - t0
    rows = []
    for v, pv in zip(tests, held.views):
        img = torch.from_numpy(np.asarray(pv.image, np.float64))
        gt = torch.from_numpy(np.asarray(v.image, np.float64)[..., :3])
        kept = torch.from_numpy(pv.valid | pv.padded)
        rows.append({"view": v.name, "valid": float(pv.valid.mean()), "kept": float(kept.float().mean()),
                     "psnr_valid": float(psnr(img, gt, torch.from_numpy(pv.valid))) if pv.valid.any() else None,
                     "psnr_kept": float(psnr(img, gt, kept)) if bool(kept.any()) else None,
                     "psnr_all": float(psnr(img, gt))})
    valid_psnr = [r["psnr_valid"] for r in rows if r["psnr_valid"] is not None]
    kept_psnr = [r["psnr_kept"] for r in rows if r["psnr_kept"] is not None]
    out = {"prior": label, "points": int(len(points)), "init_s": init_s, "pseudo_s": t_pv,
           "surface": use_surface, "consistency_tol": consistency_tol,
           "valid": float(np.mean([r["valid"] for r in rows])),
           "kept": float(np.mean([r["kept"] for r in rows])),
           "psnr_valid": float(np.mean(valid_psnr)) if valid_psnr else None,
           "psnr_kept": float(np.mean(kept_psnr)) if kept_psnr else None,
           "psnr_all": float(np.mean([r["psnr_all"] for r in rows])), "views": rows}
    if pseudo > 0:
        t0 = time.perf_counter()
        built = build_pseudo_views(train_views, points, pseudo, seed, work / "pseudo_train", surface=use_surface,
                                   consistency_tol=consistency_tol)
        wall = time.perf_counter() - t0
        fr = built.mean_fractions()
        out["_montage"] = [(pv, min(train_views, key=lambda v: float(np.linalg.norm(v.camera.center
                                                                                  - pv.camera.center))).image)
                           for pv in built.views[:2]]
        out["sampled"] = {"trajectory": built.trajectory.kind, "why": built.trajectory.reason,
                          "wanted": pseudo, "kept": len(built.views), "tried": built.tried,
                          "dropped_cloud": built.dropped_cloud, "dropped_warped": built.dropped_warped,
                          "warped": fr["warped"], "padded": fr["padded"], "rejected": fr["rejected"],
                          "cpu_s": built.cpu_s, "cpu_s_per_view": built.cpu_s / max(1, built.tried), "wall_s": wall,
                          "size": [built.views[0].camera.width, built.views[0].camera.height] if built.views else None}
    return out


def montage(results: list[dict], path: Path) -> None:
    """A PNG: one row per cloud, (nearest training photo, pseudo view) pairs; padded pixels tinted
    blue, rejected ones red."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in results if r.get("_montage")]
    if not rows:
        return
    cols = 2 * max(len(r["_montage"]) for r in rows)
    h, w = rows[0]["_montage"][0][0].image.shape[:2]
    fig, axes = plt.subplots(len(rows), cols, figsize=(2.2 * cols * w / h, 2.4 * len(rows)), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for i, r in enumerate(rows):
        for j, (pv, photo) in enumerate(r["_montage"]):
            img = np.clip(pv.image.copy(), 0, 1)
            img[pv.padded] = 0.5 * img[pv.padded] + 0.5 * np.array([0.1, 0.3, 1.0])
            if pv.rejected is not None:
                img[pv.rejected] = 0.5 * img[pv.rejected] + 0.5 * np.array([1.0, 0.1, 0.1])
            axes[i, 2 * j].imshow(np.clip(photo[..., :3], 0, 1))
            axes[i, 2 * j].set_title("nearest training photo", fontsize=7)
            axes[i, 2 * j + 1].imshow(img)
            axes[i, 2 * j + 1].set_title(f"{r['prior']}: {pv.camera.name}, {100 * pv.valid.mean():.0f}% warped",
                                         fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=60)
    plt.close(fig)


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
    sampled = [r for r in results if "sampled" in r]
    if sampled:
        lines += ["", "Pseudo views sampled as training does (trajectory, cloud-cover and warped-share filters):", "",
                  "| Cloud | trajectory | size | kept / wanted (tried) | mean warped | mean padded | mean rejected "
                  "| CPU s a view | CPU s all | wall s all |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r in sampled:
            s = r["sampled"]
            size = "x".join(map(str, s["size"])) if s["size"] else "-"
            lines.append(f"| {r['prior']} | {s['trajectory']} | {size} | {s['kept']} / {s['wanted']} ({s['tried']}) | "
                         f"{100 * s['warped']:.1f}% | {100 * s['padded']:.1f}% | {100 * s['rejected']:.1f}% | "
                         f"{s['cpu_s_per_view']:.3f} | {s['cpu_s']:.1f} | {s['wall_s']:.1f} |")
        lines += ["", f"Trajectory: {sampled[0]['sampled']['why']}"]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", type=Path)
    p.add_argument("--priors", default="mvs,gt",
                   help="comma-separated depth priors for the geometry stage (mvs, gt, depth-anything-v2); "
                        "'' with --points only")
    p.add_argument("--points", action="append", default=[], metavar="[LABEL=]PLY",
                   help="also score this dense cloud (repeatable), e.g. geom=/tmp/w/init/points.ply")
    p.add_argument("--train", default=None, help="comma-separated training view ids (default: the scene's split)")
    p.add_argument("--test", default=None, help="comma-separated held-out view ids")
    p.add_argument("--resolution-scale", type=float, default=1.0, help="views at this x their resolution")
    p.add_argument("--pseudo", type=int, default=0, metavar="N",
                   help="also build N trajectory-sampled pseudo views as training does and time them")
    p.add_argument("--mvs", action="append", default=[], metavar="FIELD=VALUE",
                   help="override an MvsConfig field (repeatable), e.g. --mvs sgm_paths=0")
    p.add_argument("--surface", choices=("auto", "on", "off"), default="auto",
                   help="complete depth holes in a height field (auto: for near-nadir views)")
    p.add_argument("--consistency-tol", type=float, default=0.0,
                   help="reject warped pixels two training views colour further apart than this (0 = keep all)")
    p.add_argument("--json", type=Path, default=None, help="also write the per-view figures here")
    p.add_argument("--png", type=Path, default=None, help="with --pseudo: a montage of sampled pseudo views")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    import torch

    torch.set_num_threads(1)
    from dibrgs_core.common.blas import single_thread_blas

    single_thread_blas()  # as the dibrgs command does
    from dibrgs_core.common.errors import InputError
    from dibrgs_core.data.ply import read_ply

    if not args.resolution_scale > 0:
        p.error(f"--resolution-scale must be > 0, got {args.resolution_scale}")
    clouds = []
    for item in args.points:
        label, _, path = item.rpartition("=")
        path = Path(path)
        if not path.is_file():
            print(f"error: {path}: --points file not found", file=sys.stderr)
            return 2
        clouds.append((label or path.parent.parent.name, path))
    mvs = {}
    for item in args.mvs:
        k, _, v = item.partition("=")
        mvs[k] = json.loads(v) if v not in ("", None) else v
    try:
        scene, train_views, tests = read(args.scene, args.train, args.test, args.resolution_scale)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    results = []
    with tempfile.TemporaryDirectory(prefix="dibrgs_pv_") as tmp:
        for prior in [x.strip() for x in args.priors.split(",") if x.strip()]:
            pts, init_s = cloud(scene, prior, Path(tmp) / prior, mvs)
            results.append(evaluate(prior, pts, train_views, tests, Path(tmp) / prior, args.surface,
                                    args.consistency_tol, args.pseudo, init_s=init_s))
        for label, path in clouds:
            pts = np.asarray(read_ply(path)[0], np.float32).astype(np.float64)
            results.append(evaluate(label, pts, train_views, tests, Path(tmp) / f"ply_{len(results)}", args.surface,
                                    args.consistency_tol, args.pseudo))
    if not results:
        p.error("nothing to score: give --priors and/or --points")
    print(table(args.scene, results))
    if args.png:
        montage(results, args.png)
    for r in results:
        r.pop("_montage", None)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
