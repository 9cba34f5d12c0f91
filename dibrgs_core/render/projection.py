"""Projection of 3D Gaussians to the image plane (EWA splatting), in plain torch.

Conventions (shared by the whole ``dibrgs_core.render`` package):

* ``viewmat`` is the 4x4 world-to-camera matrix with OpenCV axes (x right,
  y down, z forward), as ``Camera.w2c`` in ``dibrgs_core.camera.pinhole``.
* ``K`` is in pixels; pixel ``(i, j)`` covers ``[i, i+1] x [j, j+1]`` so its
  centre is ``(i + 0.5, j + 0.5)``. A camera with ``cx = W / 2`` is centred.
  The skew ``K[0, 1]`` is ignored (pinhole without skew).
* Quaternions are ``(w, x, y, z)``, normalised here; a (near-)zero quaternion
  is read as the identity rotation so its outputs and gradients stay finite.
* Scales are standard deviations along the Gaussian's axes in world units
  (activated values, not log-scales).

The maths follows 3D Gaussian Splatting as written in gsplat's pure-torch
``_fully_fused_projection``: ``Sigma = R S S^T R^T``, camera covariance
``W Sigma W^T``, the pinhole Jacobian evaluated at the camera-space mean whose
``x/z`` and ``y/z`` are clamped to the field of view widened by 30 % of its
half-width on each side, 0.3 px^2 added to the 2D covariance (low-pass
dilation), and the conic (inverse 2D covariance). The radius is 3DGS's
isotropic 3-sigma radius ``ceil(3 sqrt(lambda_max))`` in pixels.

The geometric part is evaluated in float64 whatever the input dtype, because
squared covariances of large or very close Gaussians overflow float32; the
results are cast back to the input dtype (autograd flows through the casts).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

# Low-pass dilation added to the 2D covariance, px^2 (3DGS / gsplat eps2d).
EPS2D = 0.3
# Radii are capped so that they fit an int32 whatever the Gaussian's size.
MAX_RADIUS = 1.0e9
# Quaternions with a squared norm below this are treated as the identity.
_QUAT_EPS2 = 1.0e-30


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities for one camera.

    Attributes:
        means2d: (N, 2) pixel coordinates of the projected centres (pixel
            centres at +0.5). Its gradient is kept only when the caller calls
            ``retain_grad()`` on it before backward (the densification strategies
            do while they gather statistics).
        conics: (N, 3) upper triangle ``(a, b, c)`` of the inverse 2D
            covariance, in 1/px^2; the Gaussian falls off as
            ``exp(-0.5 (a dx^2 + 2 b dx dy + c dy^2))``.
        depths: (N,) camera-space z in world units.
        radii: (N,) int32 3-sigma radius in pixels, 0 for culled Gaussians.
        visible: (N,) bool, ``radii > 0``.
    """

    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    visible: Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices (N, 3, 3) from quaternions (N, 4) in ``(w, x, y, z)`` order, any norm.

    The quaternions are divided by their norm; those with a squared norm under 1e-30
    (zero or denormal) become the identity, with zero gradient, so a nearly-zero
    quaternion still gives an orthonormal matrix.
    """
    n2 = (quats * quats).sum(-1, keepdim=True)
    ok = n2 > _QUAT_EPS2
    ident = torch.zeros_like(quats)
    ident[..., 0] = 1.0
    q = torch.where(ok, quats, ident)
    q = q / torch.where(ok, q.norm(dim=-1, keepdim=True), torch.ones_like(n2))
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1).reshape(-1, 3, 3)


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
) -> Projected:
    """Project N Gaussians with one pinhole camera.

    Args:
        means: (N, 3) world positions.
        quats: (N, 4) rotations ``(w, x, y, z)``, any norm.
        scales: (N, 3) standard deviations, world units.
        viewmat: (4, 4) world-to-camera, OpenCV axes.
        K: (3, 3) intrinsics in pixels, pixel centres at +0.5.
        width, height: image size in pixels.
        near, far: Gaussians whose camera z is not in ``(near, far)`` are
            culled (``near`` must be positive).

    Returns:
        :class:`Projected`, in the dtype of ``means``. A Gaussian is visible
        when its depth is inside ``(near, far)``, its 2D covariance is
        positive definite and its 3-sigma square overlaps the image.
    """
    if not near > 0:
        raise ValueError(f"near plane must be positive, got {near}")
    dtype = means.dtype
    f64 = torch.float64
    vm = viewmat.to(device=means.device, dtype=f64)
    Kd = K.to(device=means.device, dtype=f64)
    R_w, t_w = vm[:3, :3], vm[:3, 3]
    p = means.to(f64) @ R_w.T + t_w
    x, y, z = p.unbind(-1)
    in_depth = (z > near) & (z < far)
    # Culled Gaussians get z = 1 so that nothing divides by ~0 and their
    # (zero) upstream gradients stay zero instead of 0 * inf = NaN.
    zs = torch.where(in_depth, z, torch.ones_like(z))

    fx, fy, cx, cy = Kd[0, 0], Kd[1, 1], Kd[0, 2], Kd[1, 2]
    mx = fx * x / zs + cx
    my = fy * y / zs + cy

    # Camera-space factor Mc = W R S (covariance Mc Mc^T), as one matmul with
    # the shared camera rotation.
    M = quat_to_rotmat(quats.to(f64)) * scales.to(f64)[:, None, :]
    Mc = (R_w @ M.permute(1, 0, 2).reshape(3, -1)).reshape(3, -1, 3)  # (3 rows, N, 3)

    # Pinhole Jacobian at the mean, with x/z, y/z clamped to the widened FOV
    # (keeps the linearisation sane for Gaussians far outside the image):
    # J = [[fx/z, 0, -fx tx/z], [0, fy/z, -fy ty/z]] with tx, ty = clamped x/z, y/z.
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_xp = (width - cx) / fx + 0.3 * tan_fovx
    lim_xn = cx / fx + 0.3 * tan_fovx
    lim_yp = (height - cy) / fy + 0.3 * tan_fovy
    lim_yn = cy / fy + 0.3 * tan_fovy
    txz = torch.minimum(torch.maximum(x / zs, -lim_xn), lim_xp)
    tyz = torch.minimum(torch.maximum(y / zs, -lim_yn), lim_yp)
    u = (fx / zs)[:, None] * (Mc[0] - txz[:, None] * Mc[2])  # rows of J Mc
    v = (fy / zs)[:, None] * (Mc[1] - tyz[:, None] * Mc[2])
    # Dilated 2D covariance [[a, b], [b, c]] = J Mc Mc^T J^T + 0.3 I.
    a = (u * u).sum(-1) + EPS2D
    b = (u * v).sum(-1)
    c = (v * v).sum(-1) + EPS2D
    det = a * c - b * b
    ok_det = det > 0
    det_s = torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], dim=-1)

    # 3DGS radius: 3 sigma along the major axis.
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
        radius = torch.ceil(3.0 * torch.sqrt(lam)).clamp(max=MAX_RADIUS)
        valid = in_depth & ok_det & torch.isfinite(radius)
        inside = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        visible = valid & inside
        radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)

    means2d = torch.stack([mx, my], dim=-1).to(dtype)
    return Projected(
        means2d=means2d,
        conics=conics.to(dtype),
        depths=z.to(dtype),
        radii=radii,
        visible=visible,
    )
