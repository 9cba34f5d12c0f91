"""``dibrgs info DIR``: JSON summary of a scene (any layout ``dibrgs train`` reads).

Prints the number of views, resolution (photos of several sizes: the most common, and ``sizes``
lists each size's views), train/test split and where it came from
(``--train``/``--test``, ``split.json`` or the default), depth range, the
up axis estimated from the cameras (with its confidence), the mean angle off
nadir, the training cameras' acquisition trajectory (orbit, strips or free, and
why: what pseudo views are sampled along) and, for an orbit, the circle fitted
through the orbit views. ``no_data``: the share of each photo's pixels that hold no data
(transparent, a no-data value, masked), for the photos that have any. ``origin``: where the
scene's own frame has its (0, 0, 0) in the files' coordinates (non-zero for a scene far from its
coordinate origin, e.g. georeferenced; positions printed here, like the orbit's centre, are
relative to it). Bad input exits with code 2 and a
message naming the file.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from .options import SCENE_LAYOUTS, add_split


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="print a JSON summary of a scene", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", type=Path, help=f"scene folder ({SCENE_LAYOUTS})")
    add_split(p)
    p.set_defaults(func=run)


def summarize(scene) -> dict:
    """The JSON-serialisable summary printed by ``dibrgs info``."""
    from ..camera.frame import estimate_up, nadir_angle_deg
    from ..camera.orbit import fit_orbit
    from ..camera.trajectory import classify
    from ..data.split import orbit_ids

    cams = scene.cameras
    sizes = scene.sizes()
    up, conf = estimate_up(cams)
    out: dict = {
        "root": str(scene.root),
        "layout": scene.layout,
        "views": len(scene.views),
        # the photos' size; with photos of several sizes the most common, and ``sizes`` lists them all
        "resolution": list(next(iter(sizes))),
        "train": scene.train,
        "test": scene.test,
        "split_source": scene.split_source,
        "track_cameras": len(scene.track),
        "origin": [float(v) for v in scene.origin],
        "up": np.round(up, 6).tolist(),
        "up_confidence": round(float(conf), 6),
        "nadir_angle_deg": round(nadir_angle_deg(cams, up), 3),
    }
    if len(sizes) > 1:
        out["sizes"] = {f"{w}x{h}": ids for (w, h), ids in sizes.items()}
    no_data = {k: round(share, 4) for k, v in scene.views.items() if (share := v.no_data) > 0}
    if no_data:  # transparent, no-data or masked pixels, left out of training and scoring
        out["no_data"] = no_data
    ranges = [c.depth_range for c in cams if c.depth_range is not None and c.depth_range[1] > c.depth_range[0]]
    if ranges:
        out["depth_range_cams"] = [float(min(r[0] for r in ranges)), float(max(r[1] for r in ranges))]
    depths = [v.depth[v.depth > 0] for v in scene.views.values() if v.depth is not None]
    if depths and any(d.size for d in depths):
        allz = np.concatenate(depths)
        out["depth_range_maps"] = [float(allz.min()), float(allz.max())]
    train = [scene.views[i].camera for i in scene.train] or cams
    traj = classify(train)  # as the trainer does: the training cameras' own up axis
    out["trajectory"] = {"kind": traj.kind, "reason": traj.reason,
                         "lines": [[scene.train[i] for i in line] for line in traj.lines] if scene.train else traj.lines}
    orbit = [scene.views[i].camera for i in orbit_ids(list(scene.views))]
    if len(orbit) >= 3 and traj.kind == "orbit":
        o = fit_orbit(orbit, up)
        out["orbit"] = {k: np.round(np.asarray(v, dtype=np.float64), 6).tolist() for k, v in o.to_dict().items()}
        out["orbit"]["views"] = len(orbit)
    return out


def run(args: argparse.Namespace) -> int:
    from ..data.load import read_any_scene

    from ..common.fileio import dumps

    scene = read_any_scene(args.scene, train_ids=args.train, test_ids=args.test)
    print(dumps(summarize(scene)))
    return 0
