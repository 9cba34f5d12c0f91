"""Export trained Gaussians as a standard 3D Gaussian Splatting PLY.

The layout is the one of graphdeco-inria/gaussian-splatting's ``save_ply`` that
Gaussian viewers read: one binary little-endian ``vertex`` element with float32
properties ``x y z nx ny nz f_dc_0..2 [f_rest_0..44] opacity scale_0..2 rot_0..3``,
where ``f_dc`` is the degree-0 SH coefficient (``(rgb - 0.5) / C0``), ``f_rest``
the higher SH bands stored channel-major (all R coefficients, then G, then B),
``opacity`` the logit, ``scale_*`` the log standard deviations and ``rot_*`` the
unit quaternion (w, x, y, z). Normals are zero.

DIBR-GS's neural Gaussians are view-dependent; they are decoded once from the
training camera nearest to the mean training viewpoint, without frustum culling,
and written with colour in the DC term only (no ``f_rest``). The 3DGS baseline
writes its SH coefficients as they are.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import torch

from ..common.fileio import atomic_path

log = logging.getLogger("dibrgs.export")

SH_C0 = 0.28209479177387814


def ply_properties(n_rest: int) -> list[str]:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(n_rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def write_gaussian_ply(path: str | Path, means: np.ndarray, quats: np.ndarray, scales: np.ndarray,
                       opacities: np.ndarray, sh_dc: np.ndarray, sh_rest: np.ndarray | None = None,
                       origin: np.ndarray | None = None) -> int:
    """Write Gaussians (activated scales / opacities, SH DC (N,3), SH rest (N,K,3) or None) atomically.

    Returns the number of Gaussians written. Non-finite rows are dropped. With a non-zero
    ``origin`` (the positions are relative to it) the header says so in a line ``comment origin
    X Y Z`` (17 digits; readers skip comments).
    """
    means = np.asarray(means, np.float64).reshape(-1, 3)
    n = len(means)
    q = np.asarray(quats, np.float64).reshape(n, 4)
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    s = np.log(np.clip(np.asarray(scales, np.float64).reshape(n, 3), 1e-12, None))
    o = np.clip(np.asarray(opacities, np.float64).reshape(n), 1e-6, 1 - 1e-6)
    logit = np.log(o / (1 - o))
    dc = np.asarray(sh_dc, np.float64).reshape(n, 3)
    rest = (np.zeros((n, 0)) if sh_rest is None
            else np.asarray(sh_rest, np.float64).reshape(n, -1, 3).transpose(0, 2, 1).reshape(n, -1))
    cols = np.concatenate([means, np.zeros((n, 3)), dc, rest, logit[:, None], s, q], axis=1).astype("<f4")
    cols = cols[np.isfinite(cols).all(axis=1)]
    names = ply_properties(rest.shape[1])
    header = ["ply", "format binary_little_endian 1.0"]
    if origin is not None and np.any(origin):
        header.append("comment origin " + " ".join(repr(float(v)) for v in np.asarray(origin).reshape(3)))
    header.append(f"element vertex {len(cols)}")
    header += [f"property float {p}" for p in names]
    header += ["end_header"]
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(np.ascontiguousarray(cols).tobytes())
    return len(cols)


@torch.no_grad()
def export_ply(work: str | Path, path: str | Path) -> int:
    """Export the trained model in ``work`` to ``path``; returns the Gaussian count."""
    from .evaluate import load_trained

    tr = load_trained(work)
    if np.any(tr.origin):  # float32 positions of a georeferenced scene would lose its detail
        log.info("positions in %s are relative to (%.10g, %.10g, %.10g) of the scene's files (the scene lies far "
                 "from their coordinate origin; the header's `comment origin`): add it to place them in that frame",
                 path, *tr.origin)
    g = tr.all_gaussians()
    if "sh_dc" in g:  # spherical harmonics as they are
        dc, rest = g["sh_dc"].numpy(), g["sh_rest"].numpy()
    else:  # view-independent colours as the SH DC term
        dc, rest = (g["colors"].numpy() - 0.5) / SH_C0, None
    return write_gaussian_ply(path, g["means"].numpy(), g["quats"].numpy(), g["scales"].numpy(),
                              g["opacities"].numpy(), dc, rest, tr.origin)
