"""Fast CPU path: projection and compositing in a C++ torch extension compiled on first use.

Build and cache
    The extension (``csrc/rasterize.cpp`` with the projection ``csrc/project.h`` and the tile
    kernels ``csrc/composite.h``; for training, the loss ``csrc/ssim.h`` and ``csrc/loss.h``, the
    optimiser's step ``csrc/adam.h``, the anchors' culling, gathers, decoder and spawning
    ``csrc/spawn.h``, ``csrc/rows.h``, ``csrc/decoder.h``, the IBR projection
    ``csrc/project_rows.h``; for the pseudo views' height field, the quads' z-buffer
    ``csrc/zbuffer.h``) is compiled for the machine that runs it
    (``-march=native``: 16-lane float vectors with AVX-512, 8 with AVX2 and on AVX-512 CPUs that
    run it at half width, :mod:`..common.cpu`) by :func:`build`, which :func:`extension` calls on first
    use. Its cache lives in ``$DIBRGS_EXT_DIR`` (default ``~/.cache/dibrgs/ext``), in a folder
    named after a digest of the source bytes, the compiler (``$CXX``, default ``c++``), the flags,
    the torch and Python versions and the CPU's instruction-set flags - not of the source's path:
    the sources are copied into that folder and compiled there, so two copies of the package (a
    git checkout and the installed Blender add-on) share one build, and a cache copied to another
    CPU is rebuilt. Once built, loading it is an import (no compiler, no ninja).

    The first build takes one to two minutes. Callers that want to say so
    first check :func:`is_built` (cheap: hashes the sources, compiles nothing)
    or pass ``on_start`` to :func:`build`; a build also logs a warning on the
    ``dibrgs.render`` logger before it starts.

Failures
    When the extension cannot be built, :func:`build` raises
    :class:`BuildError`, whose message says what is missing (the compiler and
    the package that provides it, ninja, the Python headers, or the flags the
    compiler rejects) and how to choose the torch reference path instead
    (``DIBRGS_RASTERIZER=reference`` or ``render.set_backend("reference")``,
    about 100x slower). Nothing falls back silently: see
    :func:`dibrgs_core.render.set_backend`.

Environment
    ``DIBRGS_EXT_DIR`` cache root; ``CXX`` compiler; ``DIBRGS_EXT_FLAGS``
    replaces the default compile flags (``-O3 -march=native -fopenmp
    -fno-math-errno``, plus ``-DDIBRGS_VBYTES=32`` for 8-lane compositing
    vectors where :mod:`..common.cpu` finds that faster, and on Intel's Skylake family
    ``-Wa,-mbranches-within-32B-boundaries`` where the assembler takes it) for compilers that
    reject them.
"""
from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import json
import logging
import os
import platform
import sys
import sysconfig
import threading
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import torch
from torch import Tensor

from ..common.cpu import cpu_flags
from .projection import Projected
from .toolchain import (
    REFERENCE_HINT,
    BuildError,
    build_flags,
    check_prerequisites,
    compiler,
)

log = logging.getLogger("dibrgs.render")

_CSRC = Path(__file__).with_name("csrc")
_SOURCES = ("rasterize.cpp", "adam.h", "chunks.h", "composite.h", "decoder.h", "loss.h", "project.h",
            "project_rows.h", "rows.h", "spawn.h", "ssim.h", "zbuffer.h")
_NAME = "dibrgs_rasterize"
_MARKER = "built.json"
BUILD_TIME = "about 1-2 minutes"
_lock = threading.Lock()
_module: ModuleType | None = None
_error: BuildError | None = None


def _digest(flags: list[str]) -> str:
    h = hashlib.sha256()
    for name in _SOURCES:
        h.update(name.encode() + b"\0" + (_CSRC / name).read_bytes() + b"\0")
    for part in (
        torch.__version__,
        sys.implementation.cache_tag or "",
        sysconfig.get_config_var("EXT_SUFFIX") or "",
        platform.machine(),
        cpu_flags(),
        compiler(),
        " ".join(flags),
    ):
        h.update(part.encode() + b"\0")
    return h.hexdigest()[:20]


def build_dir() -> Path:
    """The cache folder of this source, compiler, flags, torch, Python and CPU (not created)."""
    root = Path(os.environ.get("DIBRGS_EXT_DIR", Path.home() / ".cache" / "dibrgs" / "ext"))
    return root / f"rasterize_{_digest(build_flags())}"


def _so_path(d: Path) -> Path | None:
    for suffix in importlib.machinery.EXTENSION_SUFFIXES + [".so"]:
        p = d / f"{_NAME}{suffix}"
        if p.is_file():
            return p
    return None


def is_built() -> bool:
    """Whether the extension is loaded or compiled in the cache (no compiling, no import)."""
    if _module is not None:
        return True
    d = build_dir()
    return (d / _MARKER).is_file() and _so_path(d) is not None


def _import(path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(_NAME, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _compile(d: Path, flags: list[str], on_start: Callable[[str], None] | None) -> ModuleType:
    from torch.utils.cpp_extension import load

    cxx = compiler()
    flags = check_prerequisites(cxx, flags)
    msg = f"compiling the C++ rasterizer for this machine (first run, {BUILD_TIME}) in {d}"
    log.warning(msg)
    if on_start is not None:
        on_start(msg)
    src = d / "src"
    src.mkdir(parents=True, exist_ok=True)
    for name in _SOURCES:  # compile a copy: the build's command lines name d only
        data = (_CSRC / name).read_bytes()
        if not (src / name).is_file() or (src / name).read_bytes() != data:
            tmp = src / f".{name}.tmp"
            tmp.write_bytes(data)
            tmp.replace(src / name)
    try:
        mod = load(
            name=_NAME,
            sources=[str(src / "rasterize.cpp")],
            extra_cflags=flags,
            extra_ldflags=["-fopenmp"] if "-fopenmp" in flags else [],
            build_directory=str(d),
            verbose=False,
        )
    except Exception as exc:
        tail = "\n".join(str(exc).strip().splitlines()[-25:])
        raise BuildError(
            f"building the C++ rasterizer with {cxx!r} failed in {d} (a too old compiler? C++17 and the "
            f"flags {' '.join(flags)} are needed); compiler output:\n{tail}\n{REFERENCE_HINT}."
        ) from exc
    info = {"simd": mod.simd(), "compiler": cxx, "flags": flags, "torch": torch.__version__}
    tmp = d / f".{_MARKER}.{os.getpid()}"
    tmp.write_text(json.dumps(info, indent=1))
    tmp.replace(d / _MARKER)
    return mod


def build(on_start: Callable[[str], None] | None = None) -> ModuleType:
    """The compiled extension, compiling it first when the cache has none.

    Args:
        on_start: called with a one-line message (what is compiled, where,
            how long it takes) just before a compile starts; not called when
            the cached build is used.

    Raises:
        BuildError: when it cannot be built (again on later calls in this process).
    """
    global _module, _error
    with _lock:
        if _module is not None:
            return _module
        if _error is not None:
            raise _error
        flags = build_flags()
        d = build_dir()
        so = _so_path(d)
        if so is not None and (d / _MARKER).is_file():
            try:
                _module = _import(so)
                return _module
            except ImportError as exc:  # a damaged cache: build again
                log.warning("rebuilding the C++ rasterizer: cached %s does not load (%s)", so, exc)
                (d / _MARKER).unlink(missing_ok=True)
        d.mkdir(parents=True, exist_ok=True)
        try:
            _module = _compile(d, flags, on_start)
        except BuildError as exc:
            _error = exc
            raise
        return _module


def extension() -> ModuleType:
    """The compiled extension module (compiling it on first call); raises :class:`BuildError`."""
    return _module if _module is not None else build()


def available(required: bool = False) -> bool:
    """Whether the C++ path builds (compiling it if needed); with ``required`` raise instead of returning False."""
    try:
        extension()
        return True
    except BuildError:
        if required:
            raise
        return False


def ready(t: Tensor, dtype: torch.dtype, detach: bool = False) -> Tensor:
    """``t`` in ``dtype`` and contiguous (detached too with ``detach``); ``t`` itself when it
    already is. The tests are attribute reads, where ``t.detach().to(dtype).contiguous()``
    dispatches three operators that change nothing, a dozen of them between a step's kernels,
    where the caches are cold."""
    if t.dtype == dtype and t.is_contiguous() and not (detach and t.requires_grad):
        return t
    return (t.detach() if detach else t).to(dtype).contiguous()


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, depth, offsets, gids, masks,  # type: ignore[override]
                width, height, groups):
        mod = extension()
        if depth is None:
            res = mod.forward(means2d, conics, opacities, feats, offsets, gids, masks, width, height, list(groups))
        else:
            res = mod.forward_colour_depth(means2d, conics, opacities, feats, depth, offsets, gids, masks, width,
                                           height, list(groups))
        *outs, tfin, ncon, rec = res
        ctx.save_for_backward(rec, offsets, gids, masks, tfin, ncon)
        ctx.size = (width, height)
        ctx.groups = list(groups)
        ctx.split = None if depth is None else feats.shape[1]
        ctx.set_materialize_grads(False)  # an unused group's gradient stays None: no zero image made
        return tuple(outs)

    @staticmethod
    def backward(ctx, *gouts):  # type: ignore[override]
        rec, offsets, gids, masks, tfin, ncon = ctx.saved_tensors
        width, height = ctx.size
        # A group without gradient is an empty tensor, read as zeros (made only then: the first
        # operator after a compositing costs tens of microseconds on the serial path).
        gm, gc, go, gf = extension().backward(rec, offsets, gids, masks,
                                              [rec.new_empty(0) if g is None else ready(g, g.dtype) for g in gouts],
                                              ctx.groups, tfin, ncon, width, height)
        c = ctx.split
        gfeat, gdepth = (gf, None) if c is None else (gf[:, :c], gf[:, c])
        return gm, gc, go, gfeat, gdepth, None, None, None, None, None, None


def composite_fast(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    feats: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    groups: tuple[int, ...],
    depth_alpha: bool = False,
) -> tuple[Tensor, ...]:
    """C++ version of :func:`reference.composite_reference` (CPU tensors, float32 or float64), its
    (H, W, C) result as one contiguous (H, W, n) tensor for each channel count of ``groups``
    (consecutive channels, summing to C; up to four): what would otherwise be strided slices
    (the renderer's colour, depth, alpha), written in place. With ``depth_alpha`` the features
    composited are ``feats`` then each Gaussian's depth (differentiable) and a one, as the
    renderer's colour, depth and alpha, without concatenating them first (``groups`` then sum to
    ``feats``' columns + 2)."""
    mod = extension()
    dt = feats.dtype
    m2, con, op, fe = ready(means2d, dt), ready(conics, dt), ready(opacities, dt), ready(feats, dt)
    dep = ready(depths, dt) if depth_alpha else None
    # The binning reads values only (no autograd below the extension's calls): nothing to detach.
    offsets, gids, masks = mod.bin_tiles(m2, con, op, depths, radii, width, height)
    return _Composite.apply(m2, con, op, fe, dep, offsets, gids, masks, width, height, tuple(groups))


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, K, viewmat, width, height, near, far):  # type: ignore[override]
        m2, con, dep, rad, vis = extension().project_forward(means, quats, scales, K, viewmat, width, height, near,
                                                             far)
        ctx.save_for_backward(means, quats, scales, K, viewmat)
        ctx.args = (width, height, near, far)
        ctx.mark_non_differentiable(rad, vis)
        ctx.set_materialize_grads(False)  # the radii's and the mask's gradients were zero tensors made every step
        return m2, con, dep, rad, vis

    @staticmethod
    def backward(ctx, g_m2, g_con, g_dep, _g_rad, _g_vis):  # type: ignore[override]
        means, quats, scales, K, viewmat = ctx.saved_tensors
        n = means.shape[0]
        g_m2 = means.new_zeros(n, 2) if g_m2 is None else ready(g_m2, g_m2.dtype)
        g_con = means.new_zeros(n, 3) if g_con is None else ready(g_con, g_con.dtype)
        # The depths' gradient is a column of the compositing's feature gradient: read with its
        # stride. None (colours alone rendered) reads as zeros in the extension.
        gm, gq, gs = extension().project_backward(means, quats, scales, K, viewmat, *ctx.args, g_m2, g_con, g_dep)
        return gm, gq, gs, None, None, None, None, None, None


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
    m2, con, dep, rad, vis = _Project.apply(
        ready(means, dt), ready(quats, dt), ready(scales, dt), ready(K, K.dtype, detach=True),
        ready(viewmat, viewmat.dtype, detach=True),
        width, height, float(near), float(far),
    )
    return Projected(means2d=m2, conics=con, depths=dep, radii=rad, visible=vis)
