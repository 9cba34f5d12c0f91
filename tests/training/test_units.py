"""Scene units do not matter: the same generated scene in millimetres-like, metre and kilometre-like
units (every camera translation, depth range and depth map scaled by 1e-3, 1 or 1e3) trains to
the same held-out PSNR."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from dibrgs_core.training.config import preset
from dibrgs_core.training.trainer import train

torch.set_num_threads(1)


def scaled_scene(src: Path, dst: Path, factor: float) -> Path:
    """A copy of the LEVIR scene ``src`` whose world is scaled by ``factor``: camera translations,
    depth ranges, track cameras and depth maps; images and intrinsics unchanged."""
    from dibrgs_core.camera.pinhole import Camera
    from dibrgs_core.data.images import read_depth, write_depth_tiff
    from dibrgs_core.data.levir import read_cams_file, write_cams_file

    shutil.copytree(src, dst)
    for folder in ("Cams", "Track"):
        for f in sorted((dst / folder).glob("*.txt")) if (dst / folder).is_dir() else []:
            c = read_cams_file(f)
            w2c = c.w2c.copy()
            w2c[:3, 3] *= factor
            dr = None if c.depth_range is None else (c.depth_range[0] * factor, c.depth_range[1] * factor)
            write_cams_file(f, Camera(K=c.K, w2c=w2c, width=c.width, height=c.height, name=c.name, depth_range=dr))
    for f in sorted((dst / "Depths").glob("*.tiff")) if (dst / "Depths").is_dir() else []:
        write_depth_tiff(f, (read_depth(f) * factor).astype(np.float32))
    return dst


def _heldout_psnr(work: Path) -> float:
    from dibrgs_core.evaluation.evaluate import evaluate

    return float(evaluate(work, fps_repeats=1, write_renders=False)["psnr"])


def test_scaled_copy_scales_the_world_only(tiny_scene, tmp_path):
    from dibrgs_core.data.levir import read_scene

    a = read_scene(tiny_scene)
    b = read_scene(scaled_scene(tiny_scene, tmp_path / "x1000", 1e3))
    for k in a.views:
        ca, cb = a.views[k].camera, b.views[k].camera
        assert np.allclose(cb.center, 1e3 * ca.center) and np.allclose(cb.R, ca.R) and np.array_equal(cb.K, ca.K)
        assert np.allclose(b.views[k].depth, 1e3 * a.views[k].depth, rtol=1e-6)
        assert np.array_equal(b.views[k].image, a.views[k].image)


@pytest.mark.slow
def test_held_out_psnr_does_not_depend_on_the_scene_units(tiny_scene, tmp_path):
    psnr = {}
    for factor in (1e-3, 1.0, 1e3):
        scene = scaled_scene(tiny_scene, tmp_path / f"scene{factor:g}", factor)
        cfg = preset("test")
        cfg.curve_every_s = 1e9
        work = tmp_path / f"work{factor:g}"
        assert train(scene, work, cfg).status == "done"
        psnr[factor] = _heldout_psnr(work)
    spread = max(psnr.values()) - min(psnr.values())
    assert spread <= 0.3, psnr
