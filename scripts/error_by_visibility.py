#!/usr/bin/env python
"""Held-out error split by how many training views see each pixel.

For a scene with true depth (a generated one), every held-out pixel is counted
as seen by 0, 1 or >= 2 training views (occlusion-tested against the training
views' true depth, :mod:`dibrgs_core.geometry.visibility`). Each trained run given is
rendered at the held-out cameras and its PSNR reported per group, pooled over
the pixels of all held-out views (so "all" is the PSNR of the pooled squared
error; "whole image", the mean of per-view PSNRs, is ``dibrgs eval``'s figure), and
"seen" pools the pixels one or more training views see (``scripts/eval_real_flight.py``'s
figure on real photos, where the plane of the reference points stands in for true depth).

    python scripts/error_by_visibility.py SCENE WORK [WORK ...] [--tol 0.01]
        [--json FILE] [--png FILE]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def split_errors(scene_dir: Path, works: list[Path], tol: float = 0.01) -> dict:
    """Visibility fractions of the held-out pixels and each run's PSNR per group, each run on its
    own split (its ``report.json``: the photos it trained on decide what counts as seen)."""
    import json

    import numpy as np

    from dibrgs_core.common.errors import InputError
    from dibrgs_core.evaluation.evaluate import load_trained
    from dibrgs_core.data.load import read_any_scene
    from dibrgs_core.geometry.visibility import SplitError, visibility_count

    splits: dict[tuple, tuple] = {}  # (train, test) -> (scene, counts, fractions)

    def of_split(train: list[str] | None, test: list[str] | None) -> tuple:
        key = (tuple(train or ()), tuple(test or ()))
        if key not in splits:
            scene = read_any_scene(scene_dir, train_ids=train, test_ids=test)  # in the runs' frame (Scene.origin)
            views = scene.train_views() + scene.test_views()
            missing = [v.name for v in views if v.depth is None or not (v.depth > 0).any()]
            if missing:
                raise InputError(scene_dir, f"views {', '.join(missing)} have no depth; the split needs true depth "
                                            "(a scene from scripts/make_scene.py has it)")
            sources = [(v.camera, v.depth) for v in scene.train_views()]
            counts = {v.name: visibility_count(v.camera, v.depth, sources, tol) for v in scene.test_views()}
            pixels = SplitError.empty()  # an exact render: only the pixel counts per group matter
            for v in scene.test_views():
                pixels.add(v.image[..., :3], v.image[..., :3], counts[v.name])
            splits[key] = (scene, counts, pixels.fractions())
        return splits[key]

    runs = []
    for w in works:
        t = load_trained(w)
        report = w / "report.json"
        rep = json.loads(report.read_text())["values"].get("scene", {}) if report.is_file() else {}
        scene, counts, fractions = of_split(rep.get("train"), rep.get("test"))
        acc, per_view = SplitError.empty(), []
        for v in scene.test_views():
            img, _ = t.render(v.camera)
            per_view.append(acc.add(img, v.image, counts[v.name]))
        runs.append({"work": str(w), "method": t.method, "psnr": acc.psnr(), "seen": acc.seen_psnr(),
                     "whole_image": float(np.mean(per_view)), "views": len(counts), "fractions": fractions})
    first = runs[0] if runs else {"views": 0, "fractions": {}}
    return {"scene": str(scene_dir), "tol": tol, "views": first["views"], "fractions": first["fractions"],
            "runs": runs}


def table(res: dict) -> str:
    def shares(r):
        f = r["fractions"]
        return (f"{r['views']} views; pixels: {f['unseen']:.1%} seen by none, {f['one']:.1%} by one, "
                f"{f['two_plus']:.1%} by two or more")

    per_run = len({shares(r) for r in res["runs"]}) > 1  # runs of other splits
    head = "per run, the runs' splits differ" if per_run else shares(res["runs"][0])
    lines = [f"Held-out PSNR (dB) of `{Path(res['scene']).name}` by how many training views see the pixel "
             f"({head}):", "",
             "| run | whole image | all | **seen** | seen by none | by one | by two or more |",
             "|---|---:|---:|---:|---:|---:|---:|"]

    def fmt(x):
        return "-" if x is None else f"{x:.2f}"

    for r in res["runs"]:
        p = r["psnr"]
        lines.append(f"| {r['work']} | {fmt(r['whole_image'])} | {fmt(p['all'])} | **{fmt(r['seen'])}** | "
                     f"{fmt(p['unseen'])} | {fmt(p['one'])} | {fmt(p['two_plus'])} |")
        if per_run:
            lines.append(f"| ({shares(r)}) | | | | | | |")
    return "\n".join(lines)


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from dibrgs_core.common.fileio import atomic_path

    groups = [("all", "all"), ("seen", "seen"), ("unseen", "seen by none"), ("one", "by one"),
              ("two_plus", "by two+")]
    n = len(res["runs"])
    fig, ax = plt.subplots(figsize=(7, 3.5))
    width = 0.8 / max(n, 1)
    for i, r in enumerate(res["runs"]):
        vals = [(r["seen"] if g == "seen" else r["psnr"][g]) or 0.0 for g, _ in groups]
        ax.bar(np.arange(len(groups)) + (i - (n - 1) / 2) * width, vals, width, label=Path(r["work"]).name)
    ax.set_xticks(range(len(groups)), [lab for _, lab in groups])
    ax.set_ylabel("held-out PSNR (dB)")
    ax.set_title(f"{Path(res['scene']).name}: error by training-view visibility")
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from dibrgs_core.common.errors import InputError
    from dibrgs_core.common.fileio import write_json

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("works", type=Path, nargs="+", help="trained run folders (dibrgs train --out)")
    ap.add_argument("--tol", type=float, default=0.01, help="relative depth tolerance of the occlusion test")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--png", type=Path, help="bar chart of the groups")
    a = ap.parse_args(argv)
    if not a.tol >= 0:
        print(f"error: --tol must be >= 0, got {a.tol}", file=sys.stderr)
        return 2
    try:
        res = split_errors(a.scene, a.works, a.tol)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(table(res))
    if a.json:
        write_json(a.json, res)
    if a.png:
        plot(res, a.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
