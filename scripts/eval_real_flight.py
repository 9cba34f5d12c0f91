#!/usr/bin/env python
"""Held-out error of trained runs on a real flight, over the pixels a training photo sees.

A real scene has no true depth, so which held-out pixels a training photo sees is decided on the
ground plane fitted to the scene's reference points (EVALUATION ONLY: the all-photo reconstruction's
points in ``reference_points.txt``, never an input of the pipeline): a held-out pixel's ray meets
the plane, and the point counts as seen by every training photo it projects into on a pixel that
holds data (masks, transparency: the runs may be scored on a copy of the scene with its training
photos' fill marked, to count only what every run could have learnt). A scene without
reference points but with depth maps for every view (a generated one, ``make_scene.py --flight
grid``) is scored the same way with its true depth instead (occlusion-tested, as
``scripts/error_by_visibility.py``). Each run is rendered at its held-out cameras at its own
resolution and scored:

* ``psnr``: mean of the per-view PSNRs over whole images (what ``dibrgs eval`` reports);
* ``seen``: PSNR of the pooled squared error over the pixels at least one training photo sees;
* ``unseen`` / ``one`` / ``two_plus``: pooled PSNR by how many training photos see the pixel.

``--warp`` adds a baseline without training: the training photos warped straight into each held-out
camera by progressive DIBR with the run's own dense cloud (``init/points.ply``; the same warp, depth
completion and consistency check that make its pseudo views), scored beside the run's render over
the pixels the warp covers. A run that does no better than this warp has learned nothing beyond its
initial geometry.

    python scripts/eval_real_flight.py SCENE WORK [WORK ...] [--reference FILE] [--json FILE]
        [--md FILE] [--png FILE] [--views NAME,NAME] [--curves FILE] [--warp]

``--png`` writes a side-by-side of two held-out photos (ground truth, then each run) with the
unseen part shaded.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def read_reference_points(path: Path) -> np.ndarray:
    """(N,3) world points of a ``reference_points.txt`` (``x y z r g b ...`` per line, ``#`` comments)."""
    rows = [line.split()[:3] for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    pts = np.asarray(rows, np.float64)
    if pts.ndim != 2 or len(pts) < 3:
        raise ValueError(f"{path}: need at least 3 points, got {len(pts)}")
    return pts


def fit_plane(points: np.ndarray, iters: int = 5) -> tuple[np.ndarray, float]:
    """Unit normal ``n`` and offset ``c`` of the plane ``n . X = c`` through ``points``: least squares,
    refitted without points beyond 3 median absolute deviations (trees, roofs)."""
    keep = np.ones(len(points), bool)
    for _ in range(iters):
        mu = points[keep].mean(0)
        n = np.linalg.svd(points[keep] - mu)[2][2]
        r = (points - mu) @ n
        mad = np.median(np.abs(r[keep] - np.median(r[keep]))) + 1e-12
        new = np.abs(r - np.median(r[keep])) <= 3.0 * 1.4826 * mad
        if new.sum() < 3 or (new == keep).all():
            break
        keep = new
    mu = points[keep].mean(0)
    n = np.linalg.svd(points[keep] - mu)[2][2]
    return n, float(n @ mu)


def plane_depth(cam, normal: np.ndarray, offset: float) -> np.ndarray:
    """(H, W) z-depth at which each pixel's ray meets the plane; 0 where it does not (in front)."""
    o, d = cam.pixel_rays()
    den = d @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (offset - o @ normal) / den
    t = np.where(np.isfinite(t) & (t > 0), t, 0.0)
    return t.reshape(cam.height, cam.width)


def resized_depth(depth: np.ndarray, cam) -> np.ndarray:
    """``depth`` (H0, W0) sampled at ``cam``'s (H, W) pixel centres, nearest neighbour (no blending
    across depth edges)."""
    H0, W0 = depth.shape
    ys = np.minimum(((np.arange(cam.height) + 0.5) * H0 / cam.height).astype(np.int64), H0 - 1)
    xs = np.minimum(((np.arange(cam.width) + 0.5) * W0 / cam.width).astype(np.int64), W0 - 1)
    return depth[ys[:, None], xs[None, :]]


def run_frames(scene_dir: Path, w: Path, t, depth: bool = False) -> tuple[list, list, dict]:
    """Training and held-out frames of run ``w`` (trained model ``t``): its split, its resolution;
    with ``depth``, also the scene's depth map of each (name -> (H, W) at the frame's size)."""
    from dibrgs_core.common.errors import InputError
    from dibrgs_core.data.load import read_any_scene
    from dibrgs_core.evaluation.evaluate import run_scale
    from dibrgs_core.training.frames import views_to_frames

    rep = json.loads((w / "report.json").read_text())["values"]["scene"]
    scene = read_any_scene(scene_dir, train_ids=rep["train"], test_ids=rep["test"], load_depth=depth)
    s = run_scale(w, t, scene)
    train, test = views_to_frames(scene.train_views(), s), views_to_frames(scene.test_views(), s)
    depths = {}
    if depth:
        for v, f in zip(scene.train_views() + scene.test_views(), train + test):
            if v.depth is None or not (v.depth > 0).any():
                raise InputError(scene_dir, f"view {v.name} has no depth map and there are no reference points: "
                                            "cannot tell which pixels a training photo sees")
            depths[v.name] = resized_depth(v.depth, f.cam.cam)
    return train, test, depths


def evaluate_runs(scene_dir: Path, works: list[Path], reference: Path | None) -> dict:
    """Score ``works`` on ``scene_dir``; visibility on the plane of ``reference``'s points, or with
    the scene's true depth when ``reference`` is None."""
    from dibrgs_core.evaluation.evaluate import load_trained
    from dibrgs_core.geometry.visibility import SplitError, visibility_count
    from dibrgs_core.training.frames import frame_valid

    points = read_reference_points(reference) if reference is not None else None
    runs, counts_of, images, loaded = [], {}, {}, {}
    for w in works:
        t = load_trained(w)
        if points is not None:  # in the run's frame (the scene's origin subtracted, as its cameras)
            normal, offset = fit_plane(points - t.origin)
        train, test, depths = run_frames(scene_dir, w, t, depth=reference is None)
        loaded[str(w)] = (t, train, test)

        def surface(cam):
            return plane_depth(cam, normal, offset) if reference is not None else depths[cam.name]

        # a training photo's pixels without data (masked, transparent) show nothing
        sources = [(f.cam.cam, surface(f.cam.cam), frame_valid(f)) for f in train]
        # What a held-out pixel's count means depends on the run's training photos: runs of other
        # splits share no counts, not even for a held-out photo they have in common.
        split_key = tuple((c.name, c.width, c.height, None if m is None else m.tobytes()) for c, _, m in sources)
        acc, per_view = SplitError.empty(), {}
        for f in test:
            cam = f.cam.cam
            key = (split_key, cam.name, cam.width, cam.height)
            if key not in counts_of:
                # The plane stands in for the surface: a looser occlusion test than with true depth.
                counts_of[key] = visibility_count(cam, surface(cam), sources,
                                                  rel_tol=0.05 if reference is not None else 0.01)
            count = counts_of[key]
            img, _ = t.render(cam)
            gt = f.image.numpy()
            per_view[cam.name] = acc.add(img, gt, count)
            images.setdefault(cam.name, {"gt": gt, "key": {}})[str(w)] = img
            images[cam.name]["key"][str(w)] = key
        p = acc.psnr()
        n_seen = acc.n["one"] + acc.n["two_plus"]
        seen = acc.seen_psnr()
        sizes = list(dict.fromkeys((f.cam.cam.width, f.cam.cam.height) for f in test))  # each size once
        runs.append({"work": str(w), "method": t.method, "preset": t.cfg.preset, "resolution": sizes,
                     "psnr": float(np.mean(list(per_view.values()))),
                     "seen": seen, "groups": p, "per_view": per_view, "fractions": acc.fractions(),
                     "seen_fraction": n_seen / max(acc.n["all"], 1)})
    vis = ({"reference": str(reference), "plane": {"normal": normal.tolist(), "offset": offset}}
           if reference is not None else {"reference": None, "visibility": "true depth"})
    return {"scene": str(scene_dir), **vis, "runs": runs, "_images": images, "_counts": counts_of,
            "_loaded": loaded}


def warp_baselines(res: dict) -> list[dict]:
    """For each run of :func:`evaluate_runs` ``res`` with a dense cloud: its training photos warped
    into its held-out cameras (progressive DIBR, the run's cloud and pseudo-view settings), and the
    pooled PSNR by visibility group of the warp and of the run's render over the pixels the warp
    covers (warped or padded)."""
    import tempfile

    from dibrgs_core.data.ply import read_ply
    from dibrgs_core.data.scene import View
    from dibrgs_core.geometry.surface import decide
    from dibrgs_core.geometry.visibility import SplitError
    from dibrgs_core.training.pseudo_views import build_pseudo_views

    rows = []
    for r in res["runs"]:
        w = Path(r["work"])
        cloud = w / "init" / "points.ply"
        if not cloud.is_file():
            print(f"note: {w}: no dense cloud ({cloud}), no warp baseline", file=sys.stderr)
            continue
        t, train, test = res["_loaded"][r["work"]]
        cams = [f.cam.cam for f in train]
        surface, _why = decide(t.cfg.pseudo.surface, cams)
        with tempfile.TemporaryDirectory() as tmp:
            built = build_pseudo_views([View(c, f.image.numpy()) for c, f in zip(cams, train)], read_ply(cloud)[0], 0,
                                       t.cfg.seed, tmp, path=[f.cam.cam for f in test], surface=surface,
                                       consistency_tol=t.cfg.pseudo.consistency_tol)
        warp, model = SplitError.empty(), SplitError.empty()
        for f, pv in zip(test, built.views):
            d = res["_images"][f.cam.cam.name]
            covered = pv.valid | pv.padded
            count = np.where(covered, res["_counts"][d["key"][str(w)]], -1)  # -1: in no group
            gt = f.image.numpy()
            warp.add(pv.image[..., :3], gt, count)
            model.add(d[str(w)], gt, count)

        n_seen = r["seen_fraction"] * warp.n["all"]
        rows.append({"work": str(w), "covered_seen": (warp.n["one"] + warp.n["two_plus"]) / max(n_seen, 1),
                     "warp": {"seen": warp.seen_psnr(), **warp.psnr()},
                     "model": {"seen": model.seen_psnr(), **model.psnr()}})
    return rows


def warp_table(rows: list[dict]) -> str:
    def fmt(x):
        return "-" if x is None else f"{x:.2f}"

    lines = ["Training photos warped into the held-out cameras with the run's dense cloud (no training), against "
             "the run's render over the same pixels (those the warp covers); PSNR in dB.", "",
             "| run | seen pixels covered | warp: seen | run: seen | warp: by one | run: by one | "
             "warp: by two or more | run: by two or more |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        a, b = r["warp"], r["model"]
        lines.append(f"| {Path(r['work']).name} | {r['covered_seen']:.1%} | {fmt(a['seen'])} | {fmt(b['seen'])} | "
                     f"{fmt(a['one'])} | {fmt(b['one'])} | {fmt(a['two_plus'])} | {fmt(b['two_plus'])} |")
    return "\n".join(lines)


def table(res: dict) -> str:
    def fmt(x):
        return "-" if x is None else f"{x:.2f}"

    def shares(r):
        f = r["fractions"]
        return f"{r['seen_fraction']:.1%} ({f['one']:.1%} by one, {f['two_plus']:.1%} by two or more)"

    runs = res["runs"]
    same = len({shares(r) for r in runs}) == 1  # one split (and resolution) for all runs
    head = (f"{shares(runs[0])} of their pixels seen by a training photo" if same else
            "the runs differ in split or resolution: the share of their pixels a training photo sees is per run")
    lines = [f"Held-out photos of `{Path(res['scene']).name}`: {head}; PSNR in dB.", "",
             "| run | method | resolution | whole image (mean of views) | seen pixels | by one | by two or more | unseen |"
             + ("" if same else " pixels seen |"),
             "|---|---|---|---:|---:|---:|---:|---:|" + ("" if same else "---:|")]
    for r in runs:
        g = r["groups"]
        res_txt = ", ".join("x".join(map(str, wh)) for wh in r["resolution"]) or "-"  # each size of the held-out photos
        lines.append(f"| {Path(r['work']).name} | {r['method']} | {res_txt} | {fmt(r['psnr'])} | {fmt(r['seen'])} | "
                     f"{fmt(g['one'])} | {fmt(g['two_plus'])} | {fmt(g['unseen'])} |" + ("" if same else
                     f" {shares(r)} |"))
    return "\n".join(lines)


def side_by_side(res: dict, path: Path, views: list[str] | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dibrgs_core.common.fileio import atomic_path

    imgs = res["_images"]
    names = views or sorted(imgs)[:2]
    runs = res["runs"]
    fig, axes = plt.subplots(len(names), 1 + len(runs), figsize=(3.2 * (1 + len(runs)), 2.0 * len(names) + 0.3),
                             squeeze=False)
    for row, name in zip(axes, names):
        d = imgs[name]
        row[0].imshow(d["gt"])
        row[0].set_title(f"{name}: ground truth", fontsize=8)
        for ax, r in zip(row[1:], runs):
            if r["work"] not in d:
                ax.set_title(f"{r['method']}: not held out", fontsize=8)
                continue
            img = d[r["work"]]
            unseen = (res["_counts"][d["key"][r["work"]]] == 0)[..., None]  # by this run's training photos
            shaded = np.where(unseen, 0.35 * img + 0.65 * np.array([0.2, 0.2, 0.5]), img)
            ax.imshow(np.clip(shaded, 0, 1))
            ax.set_title(f"{r['method']}: {r['per_view'][name]:.2f} dB", fontsize=8)
        for ax in row:
            ax.axis("off")
    fig.suptitle("held-out photos; blue-shaded: no training photo sees it", fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)


def plot_curves(works: list[Path], path: Path) -> None:
    """Held-out PSNR (the run's curve views) against training wall-clock seconds, one line a run."""
    import csv

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dibrgs_core.common.fileio import atomic_path

    fig, ax = plt.subplots(figsize=(6, 3.6))
    for w in works:
        rows = list(csv.DictReader((w / "curve.csv").open()))
        cfg = json.loads((w / "config.json").read_text())["config"]
        ax.plot([float(r["seconds"]) for r in rows], [float(r["psnr"]) for r in rows], marker=".",
                label=f"{w.name} ({cfg['method']}, {cfg['iterations']} it)")
    ax.set_xlabel("training wall-clock seconds (evaluation excluded)")
    ax.set_ylabel("held-out PSNR, whole image (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from dibrgs_core.common.errors import InputError
    from dibrgs_core.common.fileio import write_json, write_text

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("works", type=Path, nargs="+", help="trained run folders (dibrgs train --out)")
    ap.add_argument("--reference", type=Path, default=None,
                    help="reference points (default SCENE/reference_points.txt; without them, the scene's depth maps)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--md", type=Path, help="write the table here")
    ap.add_argument("--png", type=Path, help="side-by-side of two held-out photos")
    ap.add_argument("--views", default=None, help="comma-separated held-out photo names for --png")
    ap.add_argument("--curves", type=Path, help="held-out PSNR against training time of every run (PNG)")
    ap.add_argument("--warp", action="store_true",
                    help="also score the training photos warped into the held-out cameras with each run's cloud")
    a = ap.parse_args(argv)
    ref = a.reference or a.scene / "reference_points.txt"
    if not ref.is_file():
        if a.reference is not None:
            print(f"error: {ref}: reference points not found", file=sys.stderr)
            return 2
        ref = None  # a generated scene: its true depth decides what a training photo sees
    try:
        res = evaluate_runs(a.scene, a.works, ref)
    except (InputError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    text = table(res)
    if a.warp:
        res["warp"] = warp_baselines(res)
        text += "\n\n" + warp_table(res["warp"])
    print(text)
    if a.md:
        write_text(a.md, text + "\n")
    if a.png:
        side_by_side(res, a.png, a.views.split(",") if a.views else None)
    if a.curves:
        plot_curves(a.works, a.curves)
    if a.json:
        write_json(a.json, {k: v for k, v in res.items() if not k.startswith("_")})
    return 0


if __name__ == "__main__":
    sys.exit(main())
