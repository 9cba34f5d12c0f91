"""The C++ compositing kernels beyond the common tests: the per-row segment culling never
drops a pixel that composites (thin, oblique Gaussians at every angle, tile and segment
borders, partial tiles), the pair counts the benchmark reports are exact, and the
run-time channel count path has the same gradients as the reference."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from dibrgs_core.render import composite, project_gaussians, rasterize
from rasterizer_oracle import brute_composite
from threads import torch_threads

W, H = 70, 53


def box_means(g: torch.Generator, n: int, size: list[float], low: list[float]) -> torch.Tensor:
    """n float64 points uniform in the box from ``low`` to ``low + size``."""
    f64 = torch.float64
    return torch.rand(n, 3, generator=g, dtype=f64) * torch.tensor(size, dtype=f64) + torch.tensor(low, dtype=f64)


def thin_scene(n: int, seed: int, dtype):
    """Needle-like Gaussians at random 3D orientations, many crossing tile and segment borders."""
    g = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    means = box_means(g, n, [3.0, 2.4, 1.0], [-1.5, -1.2, 4.0])
    quats = torch.randn(n, 4, generator=g, dtype=f64)
    scales = torch.stack(
        [
            torch.rand(n, generator=g, dtype=f64) * 0.6 + 0.05,
            torch.rand(n, generator=g, dtype=f64) * 0.02 + 0.002,
            torch.rand(n, generator=g, dtype=f64) * 0.02 + 0.002,
        ],
        -1,
    )
    opac = torch.rand(n, generator=g, dtype=f64) * 0.95 + 0.02
    feats = torch.rand(n, 3, generator=g, dtype=f64)
    vm = torch.eye(4, dtype=f64)
    K = torch.tensor([[40.0, 0, 33.7], [0, 42.0, 27.2], [0, 0, 1]], dtype=f64)
    proj = project_gaussians(means, quats, scales, vm, K, W, H)
    feats = torch.cat([feats, torch.ones(n, 1, dtype=f64)], 1)
    return [t.detach().to(dtype) if t.is_floating_point() else t for t in
            (proj.means2d, proj.conics, opac, feats, proj.depths, proj.radii)]


@pytest.mark.parametrize("dtype,atol", [(torch.float32, 1e-5), (torch.float64, 1e-9)])
def test_segment_culling_keeps_every_contributing_pixel(dtype, atol):
    from dibrgs_core.render import fast

    m2, con, op, feats, dep, rad = thin_scene(160, 3, dtype)
    assert int((rad > 0).sum()) > 120
    out = composite(m2, con, op, feats, dep, rad, W, H, backend="fast")
    ref, count = brute_composite(m2, con, op, feats, dep, rad, W, H, return_count=True)
    assert ref[..., -1].max() > 0.9
    np.testing.assert_allclose(out.numpy(), ref, atol=atol, rtol=0)

    # The culling is real: far fewer pixels evaluated than the listed tiles hold.
    mod = fast.extension()
    offsets, gids, masks = mod.bin_tiles(m2, con, op, dep, rad, W, H)
    _, tfin, ncon, rec = mod.forward(m2, con, op, feats, offsets, gids, masks, W, H, [feats.shape[1]])
    stats = mod.composite_stats(rec, offsets, gids, masks, torch.ones(H, W, feats.shape[1], dtype=dtype), W, H)
    vectors, lanes, contrib, _, entries = stats[0].tolist()
    assert lanes < 0.5 * entries * 256
    # Counts are exact: the pairs composited are the brute force's, the backward
    # carries a gradient through each of them.
    if dtype == torch.float64:
        assert contrib == count
    else:
        assert abs(contrib - count) <= 1e-3 * count
    assert stats[1, 2] == contrib and contrib <= lanes <= vectors * (64 // op.element_size())


def test_segment_masks_change_no_result_for_thin_gaussians():
    """Culling saves work and never changes a result: for needles as thin as the projection's
    low-pass allows and 50-500 px long (conic condition numbers up to about 1e6, where float32's
    test of q near the ellipse's edge is least exact), the kernels given the tiles' segment masks
    return exactly what they return evaluating every segment of the listed tiles, forward and
    backward."""
    from dibrgs_core.render import fast

    g = torch.Generator().manual_seed(7)
    f64 = torch.float64
    n = 300
    means = box_means(g, n, [1.0, 0.8, 1.0], [-0.5, -0.4, 4.0])
    quats = torch.randn(n, 4, generator=g, dtype=f64)
    scales = torch.stack([torch.rand(n, generator=g, dtype=f64) * 4.5 + 0.5, torch.full((n,), 1e-4, dtype=f64),
                          torch.full((n,), 1e-4, dtype=f64)], -1)
    K = torch.tensor([[400.0, 0, 35.0], [0, 400.0, 26.5], [0, 0, 1]], dtype=f64)
    proj = project_gaussians(means, quats, scales, torch.eye(4, dtype=f64), K, W, H)
    a, b, c = proj.conics.T
    h, d = (a + c) / 2, torch.hypot((a - c) / 2, b)
    assert float(((h + d) / (h - d)).max()) > 3e5
    f32 = torch.float32
    m2, con, dep = (t.detach().to(f32).contiguous() for t in (proj.means2d, proj.conics, proj.depths))
    op = (torch.rand(n, generator=g, dtype=f64) * 0.95 + 0.02).to(f32)
    feats = torch.rand(n, 4, generator=g, dtype=f64).to(f32)
    mod = fast.extension()
    offsets, gids, masks = mod.bin_tiles(m2, con, op, dep, proj.radii, W, H)
    every = torch.full_like(masks, -1)
    assert int((masks != -1).sum()) > 0.3 * len(masks)  # the masks do cull
    outs = [mod.forward(m2, con, op, feats, offsets, gids, mk, W, H, [4]) for mk in (masks, every)]
    for x, y in zip(outs[0][:3], outs[1][:3]):
        assert torch.equal(x, y)
    assert float(outs[0][2].max()) > 0 and float(outs[0][0][..., 3].max()) > 0.5
    gout = torch.rand(H, W, 4, generator=g, dtype=f64).to(f32)
    grads = [mod.backward(o[3], offsets, gids, mk, [gout], [4], o[1], o[2], W, H) for o, mk in zip(outs, (masks, every))]
    for x, y in zip(*grads):
        assert torch.equal(x, y)
    assert float(grads[0][0].abs().sum()) > 0


def test_runtime_channel_count_matches_reference_gradients():
    """4 channels (2 colours + depth + alpha) run the kernels with the count at run time."""
    g = torch.Generator().manual_seed(11)
    f64 = torch.float64
    n = 90
    means = torch.randn(n, 3, generator=g, dtype=f64) * torch.tensor([1.0, 0.8, 0.5], dtype=f64)
    means[:, 2] += 4.0
    quats = torch.randn(n, 4, generator=g, dtype=f64)
    scales = torch.rand(n, 3, generator=g, dtype=f64) * 0.3 + 0.02
    opac = torch.rand(n, generator=g, dtype=f64) * 0.9
    cols = torch.rand(n, 2, generator=g, dtype=f64)
    vm = torch.eye(4, dtype=f64)
    K = torch.tensor([[30.0, 0, 20.0], [0, 30.0, 17.0], [0, 0, 1]], dtype=f64)
    wgt = torch.rand(34, 41, 2, generator=g, dtype=f64)
    grads = []
    for backend in ("reference", "fast"):
        ps = [t.clone().requires_grad_() for t in (means, quats, scales, opac, cols)]
        img, alpha, depth, _ = rasterize(*ps, vm, K, 41, 34, backend=backend)
        ((img * wgt).sum() + alpha.sum() + 0.1 * depth.sum()).backward()
        grads.append([p.grad for p in ps])
    for a, b in zip(*grads):
        assert a.abs().sum() > 0
        torch.testing.assert_close(b, a, rtol=1e-7, atol=1e-9)


def test_many_gaussians_stop_early_and_match():
    """Dense, opaque layers: pixels stop at T < 1e-4 long before the tile lists end,
    and the fast path still equals the brute force."""
    g = torch.Generator().manual_seed(5)
    f64 = torch.float64
    n = 400
    means = box_means(g, n, [2.0, 2.0, 3.0], [-1.0, -1.0, 3.0])
    quats = torch.randn(n, 4, generator=g, dtype=f64)
    scales = torch.rand(n, 3, generator=g, dtype=f64) * 0.3 + 0.1
    opac = torch.full((n,), 0.97, dtype=f64)
    cols = torch.rand(n, 3, generator=g, dtype=f64)
    vm = torch.eye(4, dtype=f64)
    K = torch.tensor([[40.0, 0, 17.0], [0, 40.0, 16.0], [0, 0, 1]], dtype=f64)
    proj = project_gaussians(means, quats, scales, vm, K, 34, 32)
    feats = torch.cat([cols, torch.ones(n, 1, dtype=f64)], 1)
    args = (proj.means2d.detach(), proj.conics.detach(), opac, feats, proj.depths.detach(), proj.radii)
    ref = brute_composite(*args, 34, 32)
    assert (ref[..., -1] > 0.999).mean() > 0.5  # most pixels saturate (T stops near 1e-4)
    out = composite(*args, 34, 32, backend="fast")
    np.testing.assert_allclose(out.numpy(), ref, atol=1e-9, rtol=0)
    assert math.isfinite(float(out.sum()))
    # The forward visits fewer list entries than the tiles hold (early exit per segment).
    from dibrgs_core.render import fast

    mod = fast.extension()
    offsets, gids, masks = mod.bin_tiles(*args[:3], args[4], args[5], 34, 32)
    _, _, _, rec = mod.forward(*args[:4], offsets, gids, masks, 34, 32, [args[3].shape[1]])
    stats = mod.composite_stats(rec, offsets, gids, masks, torch.ones(32, 34, 4, dtype=f64), 34, 32)
    assert stats[0, 3] < 0.7 * stats[0, 4]


def test_tile_lists_do_not_depend_on_threads_or_input_types():
    """Binning 30,000 Gaussians (parallel culling, the sort's halves and merge, chunked emission):
    the same lists on 1, 2 and 3 threads, for float32 / float64 inputs and int32 / int64 radii;
    each tile's list in increasing depth with ties by index (many exact ties here); a Gaussian
    with a non-finite centre, zero opacity or zero radius is in no list."""
    from dibrgs_core.render import fast

    mod = fast.extension()
    g = torch.Generator().manual_seed(3)
    n, w, h = 30000, 200, 150
    m2 = torch.rand(n, 2, generator=g) * torch.tensor([w + 40.0, h + 40.0]) - 20.0
    a, c = torch.rand(n, generator=g) * 0.5 + 0.01, torch.rand(n, generator=g) * 0.5 + 0.01
    b = (torch.rand(n, generator=g) - 0.5) * torch.sqrt(a * c)  # positive definite
    con = torch.stack([a, b, c], 1)
    op = torch.rand(n, generator=g) * 0.98 + 0.01
    dep = torch.randint(1, 400, (n,), generator=g).float() * 0.25  # exact ties
    rad = torch.ceil(3.0 / torch.sqrt(torch.minimum(a, c))).to(torch.int32)
    m2[5, 0], op[6], rad[7] = float("nan"), 0.0, 0
    runs = {}
    for nt in (1, 2, 3):
        with torch_threads(nt):
            runs[nt] = mod.bin_tiles(m2, con, op, dep, rad, w, h)
            # int64 radii, and float32 values held in float64 tensors, read the same
            same = mod.bin_tiles(m2.double(), con.double(), op.double(), dep.double(), rad.long(), w, h)
            assert torch.equal(same[0], runs[nt][0]) and torch.equal(same[1], runs[nt][1])
            # a mix of dtypes is read as float64: the lists as float32's, the masks laid out for means2d's
            mixed = mod.bin_tiles(m2, con.double(), op, dep, rad, w, h)
            assert all(torch.equal(x, y) for x, y in zip(mixed, runs[nt]))
    for nt in (2, 3):
        assert all(torch.equal(x, y) for x, y in zip(runs[nt], runs[1]))
    offsets, gids, _ = runs[1]
    assert gids.numel() > 2 * n
    ids = gids.long().numpy()
    d = dep.numpy()[ids]
    tile = np.repeat(np.arange(offsets.numel() - 1), np.diff(offsets.numpy()))
    inside = tile[1:] == tile[:-1]
    ordered = (d[1:] > d[:-1]) | ((d[1:] == d[:-1]) & (ids[1:] > ids[:-1]))
    assert ordered[inside].all()
    assert ((d[1:] == d[:-1]) & inside).sum() > 1000  # the ties were exercised
    assert not np.isin([5, 6, 7], ids).any()
    # nothing to bin, or an image without pixels: empty lists
    for args, size in (((m2[:0], con[:0], op[:0], dep[:0], rad[:0]), (w, h)), ((m2, con, op, dep, rad), (0, h))):
        off, ids_, _ = mod.bin_tiles(*args, *size)
        assert ids_.numel() == 0 and int(off[-1]) == 0


def test_projection_does_not_depend_on_threads():
    """The projection's runs of Gaussians pulled by the threads (whole vectors, then a scalar tail
    at the end only): means2d, conics, depths, radii and the three gradients equal the one-thread
    result bit for bit on 2 and 3 threads, for 20,003 Gaussians (a tail) in front of and behind
    the camera."""
    from dibrgs_core.render import fast

    mod = fast.extension()
    g = torch.Generator().manual_seed(5)
    n = 20003
    means = torch.randn(n, 3, generator=g) * torch.tensor([4.0, 3.0, 6.0]) + torch.tensor([0.0, 0.0, 5.0])
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.3 + 0.01
    K = torch.tensor([[120.0, 0.0, 80.0], [0.0, 120.0, 60.0], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    grads = [torch.randn(n, 2, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, generator=g)]
    runs = {}
    for nt in (1, 2, 3):
        with torch_threads(nt):
            out = mod.project_forward(means, quats, scales, K, w2c, 160, 120, 0.01, 1e10)
            back = mod.project_backward(means, quats, scales, K, w2c, 160, 120, 0.01, 1e10, *grads)
            runs[nt] = [*out, *back]
    assert 0 < int(runs[1][4].sum()) < n  # some culled, some kept
    for nt in (2, 3):
        for i, (a, b) in enumerate(zip(runs[1], runs[nt])):
            assert torch.equal(a, b), (nt, i)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_projection_backward_without_a_depth_gradient_reads_zeros(dtype):
    """A colours-only render passes no depth gradient (None) to the projection's backward: the
    gradients equal those from a depth gradient of zeros, bit for bit, and differ from a nonzero
    one (the depth gradient is read at all)."""
    from dibrgs_core.render import fast

    mod = fast.extension()
    g = torch.Generator().manual_seed(11)
    n = 1001
    means = (torch.randn(n, 3, generator=g) * torch.tensor([2.0, 1.5, 1.0]) + torch.tensor([0.0, 0.0, 6.0])).to(dtype)
    quats = torch.randn(n, 4, generator=g).to(dtype)
    scales = (torch.rand(n, 3, generator=g) * 0.3 + 0.01).to(dtype)
    K = torch.tensor([[120.0, 0.0, 80.0], [0.0, 120.0, 60.0], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    gm2, gcon = torch.randn(n, 2, generator=g).to(dtype), torch.randn(n, 3, generator=g).to(dtype)
    args = (means, quats, scales, K, w2c, 160, 120, 0.01, 1e10, gm2, gcon)
    without = mod.project_backward(*args, None)
    zeros = mod.project_backward(*args, torch.zeros(n, dtype=dtype))
    some = mod.project_backward(*args, torch.randn(n, generator=g).to(dtype))
    for a, b in zip(without, zeros):
        assert torch.equal(a, b)
    assert not torch.equal(without[0], some[0])
    with pytest.raises(RuntimeError, match="depths"):
        mod.project_backward(*args, torch.zeros(n + 1, dtype=dtype))
