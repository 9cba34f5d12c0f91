"""Fast CPU path: projection and compositing in a C++ torch extension compiled on first use.

The extension (``csrc/rasterize.cpp``) is built with
``torch.utils.cpp_extension.load`` (ninja) into ``$DIBRGS_EXT_DIR`` or
``~/.cache/dibrgs/ext``, in a folder named after a hash of the source, the
torch version and the CPU's instruction-set flags: it is compiled with
``-march=native`` for the machine that runs it, and a cache copied to another
CPU is rebuilt rather than reused. When ``-march=native`` does not build the
portable ``-O3`` flags are tried; when nothing builds (no compiler) a warning
says so and :func:`available` is False, so ``rasterize`` uses the reference.
"""
from __future__ import annotations

import hashlib
import logging
import os
import platform
import threading
from pathlib import Path
from types import ModuleType

import torch
from torch import Tensor

from .projection import Projected

log = logging.getLogger("dibrgs.render")

_SRC = Path(__file__).with_name("csrc") / "rasterize.cpp"
_lock = threading.Lock()
_module: ModuleType | None = None
_error: str | None = None


def _cpu_flags() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return " ".join(sorted(line.split(":", 1)[1].split()))
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _build_dir(tag: str, flags: list[str]) -> Path:
    root = Path(os.environ.get("DIBRGS_EXT_DIR", Path.home() / ".cache" / "dibrgs" / "ext"))
    h = hashlib.sha256()
    for part in (_SRC.read_bytes(), torch.__version__.encode(), _cpu_flags().encode(), " ".join(flags).encode()):
        h.update(part)
    d = root / f"rasterize_{tag}_{h.hexdigest()[:16]}"
    d.mkdir(parents=True, exist_ok=True)
    return d


def _load() -> ModuleType:
    from torch.utils.cpp_extension import load

    errors = []
    # -fopenmp is needed for at::parallel_for (an inline header template) to
    # run in parallel at all; torch's own OpenMP runtime is the one linked.
    # No -ffast-math: the kernels rely on IEEE comparisons for culled lanes.
    common = ["-O3", "-fopenmp", "-fno-math-errno"]
    for tag, flags in (("native", common + ["-march=native", "-mprefer-vector-width=512"]), ("portable", common)):
        try:
            return load(
                name=f"dibrgs_rasterize_{tag}",
                sources=[str(_SRC)],
                extra_cflags=flags,
                extra_ldflags=["-fopenmp"],
                build_directory=str(_build_dir(tag, flags)),
                verbose=False,
            )
        except Exception as exc:  # compiler missing or rejecting the flags
            errors.append(f"{tag}: {exc}")
    raise RuntimeError("; ".join(errors))


def extension() -> ModuleType:
    """The compiled extension module (compiling it on first call).

    Raises:
        RuntimeError: when it cannot be built.
    """
    global _module, _error
    with _lock:
        if _module is None and _error is None:
            try:
                _module = _load()
            except Exception as exc:
                _error = str(exc)
                log.warning(
                    "could not build the C++ rasterizer (%s); using the slower torch reference path",
                    _error.splitlines()[0][:500],
                )
        if _module is None:
            raise RuntimeError(f"C++ rasterizer unavailable: {_error}")
        return _module


def available(required: bool = False) -> bool:
    """Whether the C++ path can be used; with ``required`` raise instead of returning False."""
    try:
        extension()
        return True
    except RuntimeError:
        if required:
            raise
        return False


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, offsets, gids, ext, width, height):  # type: ignore[override]
        mod = extension()
        out, tfin, ncon = mod.forward(means2d, conics, opacities, feats, offsets, gids, ext, width, height)
        ctx.save_for_backward(means2d, conics, opacities, feats, offsets, gids, ext, tfin, ncon)
        ctx.size = (width, height)
        return out

    @staticmethod
    def backward(ctx, gout):  # type: ignore[override]
        means2d, conics, opacities, feats, offsets, gids, ext, tfin, ncon = ctx.saved_tensors
        width, height = ctx.size
        gm, gc, go, gf = extension().backward(
            means2d, conics, opacities, feats, offsets, gids, ext, gout.contiguous(), tfin, ncon, width, height
        )
        return gm, gc, go, gf, None, None, None, None, None


def composite_fast(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    feats: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
) -> Tensor:
    """C++ version of :func:`reference.composite_reference` (CPU tensors, float32 or float64)."""
    mod = extension()
    dt = feats.dtype
    m2 = means2d.to(dt).contiguous()
    con = conics.to(dt).contiguous()
    op = opacities.to(dt).contiguous()
    fe = feats.contiguous()
    offsets, gids, ext = mod.bin_tiles(m2.detach(), con.detach(), op.detach(), depths.detach(), radii, width, height)
    return _Composite.apply(m2, con, op, fe, offsets, gids, ext, width, height)


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, cam, width, height, near, far):  # type: ignore[override]
        m2, con, dep, rad = extension().project_forward(means, quats, scales, cam, width, height, near, far)
        ctx.save_for_backward(means, quats, scales, cam)
        ctx.args = (width, height, near, far)
        ctx.mark_non_differentiable(rad)
        return m2, con, dep, rad

    @staticmethod
    def backward(ctx, g_m2, g_con, g_dep, _g_rad):  # type: ignore[override]
        means, quats, scales, cam = ctx.saved_tensors
        grads = [
            torch.zeros_like(ref) if g is None else g.contiguous()
            for g, ref in ((g_m2, means[:, :2]), (g_con, means), (g_dep, means[:, 0]))
        ]
        gm, gq, gs = extension().project_backward(means, quats, scales, cam, *ctx.args, *grads)
        return gm, gq, gs, None, None, None, None, None


def project_fast(
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
    """C++ version of :func:`projection.project_gaussians` (CPU tensors, same maths and outputs).

    Every per-Gaussian quantity is computed in float64 inside, whatever the
    dtype of ``means``; outputs are in that dtype. Gradients flow to means,
    quats and scales (not to ``viewmat`` or ``K``).
    """
    if not near > 0:
        raise ValueError(f"near plane must be positive, got {near}")
    dt = means.dtype
    vm = viewmat.detach().to(device="cpu", dtype=torch.float64)
    Kd = K.detach().to(device="cpu", dtype=torch.float64)
    cam = torch.cat([vm[:3, :3].reshape(-1), vm[:3, 3], torch.stack([Kd[0, 0], Kd[1, 1], Kd[0, 2], Kd[1, 2]])])
    m2, con, dep, rad = _Project.apply(
        means.contiguous(), quats.to(dt).contiguous(), scales.to(dt).contiguous(), cam.contiguous(),
        width, height, float(near), float(far),
    )
    if m2.requires_grad:
        m2.retain_grad()
    return Projected(means2d=m2, conics=con, depths=dep, radii=rad, visible=rad > 0)
