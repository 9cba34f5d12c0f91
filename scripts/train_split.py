#!/usr/bin/env python
"""Train one method on a scene with a chosen train / test split, then score the held-out views.

    python scripts/train_split.py SCENE WORK [--method 3dgs] [--preset cpu]
        [--train 001,003,...] [--test 002,005,...] [--set gs3d.min_reset_every=0 ...]
        [--json FILE]

``--train`` / ``--test`` take view ids or names as the scene has them (LEVIR ids such as
``001``); without them the scene's own split is used. ``--set`` overrides a configuration
field (``name=value`` or ``part.name=value``, the value read as JSON when it parses).

Scoring is ``dibrgs eval``'s: scikit-image PSNR and SSIM (Gaussian window, sigma 1.5) of
the clamped renders against the held-out images at the run's resolution, averaged over
the views. The result (and the run's report entries on the split and the colour
transforms) is printed as one JSON object and optionally written to ``--json``.

Until ``split.json`` and ``--train``/``--test`` reach ``dibrgs train``, the split is
handed to the trainer by replacing the scene reader of :mod:`dibrgs_core.training.trainer`
for this process only.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def apply_overrides(cfg, sets: list[str]) -> None:
    for s in sets:
        key, _, val = s.partition("=")
        obj = cfg
        *parts, last = key.split(".")
        for p in parts:
            obj = getattr(obj, p)
        if not hasattr(obj, last):
            raise SystemExit(f"train_split.py: --set {key}: no such configuration field")
        v = _value(val)
        setattr(obj, last, tuple(v) if isinstance(v, list) else v)


def score(work: Path, test_views) -> dict:
    import numpy as np
    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from dibrgs_core.evaluation.evaluate import load_trained
    from dibrgs_core.training.frames import views_to_frames

    tr = load_trained(work)
    frames = views_to_frames(test_views, tr.cfg.resolution_scale)
    ps, ss = [], []
    for f in frames:
        img, _ = tr.render(f.cam.cam)
        gt = f.image.numpy()
        ps.append(float(peak_signal_noise_ratio(gt, img, data_range=1.0)))
        ss.append(float(structural_similarity(gt, img, channel_axis=2, data_range=1.0, gaussian_weights=True,
                                              sigma=1.5, use_sample_covariance=False)))
    return {"psnr": float(np.mean(ps)), "ssim": float(np.mean(ss)), "views": len(frames),
            "per_view_psnr": dict(zip([f.cam.cam.name for f in frames], ps))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("work", type=Path)
    ap.add_argument("--method", default="dibrgs")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--train", default=None, help="comma-separated training view ids")
    ap.add_argument("--test", default=None, help="comma-separated held-out view ids")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    import torch

    from dibrgs_core.data.load import read_any_scene
    from dibrgs_core.training import trainer as trainer_module
    from dibrgs_core.training.config import preset

    torch.set_num_threads(args.threads)
    train_ids = args.train.split(",") if args.train else None
    test_ids = args.test.split(",") if args.test else None
    scene = read_any_scene(args.scene, train_ids=train_ids, test_ids=test_ids)
    trainer_module.load_scene = lambda root: read_any_scene(root, train_ids=train_ids, test_ids=test_ids)

    cfg = preset(args.preset)
    cfg.method = args.method
    apply_overrides(cfg, args.set)
    t0 = time.time()
    res = trainer_module.train(args.scene, args.work, cfg)
    wall = time.time() - t0
    out = {"scene": str(args.scene), "work": str(args.work), "method": args.method, "preset": args.preset,
           "set": args.set, "train": list(scene.train), "test": list(scene.test), "status": res.status,
           "train_seconds": res.seconds, "wall_seconds": wall, **res.sizes}
    if res.status == "done":
        out.update(score(args.work, scene.test_views()))
    rep = json.loads((args.work / "report.json").read_text())
    for key in ("colour_transforms", "resolution", "opacity_resets"):
        if key in rep.get("values", {}):
            out[key] = rep["values"][key]
    text = json.dumps(out, indent=1)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
