"""Height map: percentile bound, relaxation above ground, empty cells, torch/numpy queries, npz."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from dibrgs_core.camera.frame import up_frame
from dibrgs_core.common.errors import InputError
from dibrgs_core.geometry.height_map import HeightMap


def _cloud():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 30, (6000, 2))
    h = np.where(xy[:, 0] < 10, 20.0, 0.0) + rng.uniform(0, 1, 6000)  # a 20-high block on the left
    keep = ~((xy[:, 0] > 20) & (xy[:, 1] > 20))  # one empty corner
    return np.column_stack([xy, h])[keep]


def test_bounds_and_allows_numpy_and_torch(tmp_path):
    pts = _cloud()
    hm = HeightMap.build(pts, np.eye(3), np.zeros(3), cell=10.0, percentile=95, relax=1.1, margin=0.0)
    assert hm.bounds.shape == (3, 3) and np.isfinite(hm.bounds).all()
    # bound = ground + 1.1 * (p95 - ground); ground ~ 2nd percentile of heights (~0.03).
    assert 22.5 < hm.bounds[0, 0] < 23.5  # 0.03 + 1.1 * (20.95 - 0.03)
    assert 0.9 < hm.bounds[2, 0] < 1.2
    # The empty corner cell takes a neighbour's bound (the flat part).
    assert hm.bounds[2, 2] == pytest.approx(hm.bounds[2, 1]) or hm.bounds[2, 2] == pytest.approx(hm.bounds[1, 2])
    q = np.array([[5, 5, 21.0], [5, 5, 30.0], [25, 5, 0.5], [25, 5, 5.0], [25, 25, 0.5], [-100, 5, 21.0],
                  [np.nan, 0, 0]])
    want = [True, False, True, False, True, True, False]
    assert hm.allows(q).tolist() == want
    assert hm.allows(torch.tensor(q, dtype=torch.float32)).tolist() == want
    assert hm.allows(torch.tensor(q, dtype=torch.float64)).dtype == torch.bool
    hm.save(tmp_path / "h.npz")
    hm2 = HeightMap.load(tmp_path / "h.npz")
    assert np.array_equal(hm2.bounds, hm.bounds) and hm2.allows(q).tolist() == want


@pytest.mark.stability
def test_negative_heights_and_other_up_axis():
    """Up = -Y, georeferenced origin, all heights negative: relaxation still loosens the bound."""
    up = np.array([0.0, -1.0, 0.0])
    F = up_frame(up)
    origin = np.array([3.0e5, 5.0e3, 4.0e5])
    rng = np.random.default_rng(2)
    loc = np.column_stack([rng.uniform(0, 20, 2000), rng.uniform(0, 20, 2000), rng.uniform(-60, -50, 2000)])
    world = loc @ F + origin
    hm = HeightMap.build(world, F, origin, cell=10.0, relax=1.5)
    p95 = np.percentile(loc[:, 2], 95)
    assert (hm.bounds > p95 - 0.5).all()  # relaxed upward, not tightened by the negative sign
    top = world[np.argmax(loc[:, 2])]
    assert hm.allows(top[None])[0]
    assert not hm.allows((top + 30 * up)[None])[0]
    assert hm.allows(torch.tensor(world)).float().mean() > 0.95


@pytest.mark.stability
def test_all_heights_equal_and_margin():
    """Height map when every height is equal: finite bounds, points at that height allowed."""
    pts = np.column_stack([np.random.default_rng(0).uniform(0, 30, (500, 2)), np.full(500, 7.0)])
    hm = HeightMap.build(pts, np.eye(3), np.zeros(3), cell=10.0, margin=0.5)
    assert np.allclose(hm.bounds, 7.5)
    assert hm.allows(np.array([[3, 3, 7.4], [3, 3, 7.6]])).tolist() == [True, False]


def test_bad_inputs(tmp_path):
    with pytest.raises(ValueError):
        HeightMap.build(np.full((3, 3), np.nan), np.eye(3), np.zeros(3), 10.0)
    (tmp_path / "x.npz").write_bytes(b"not an npz")
    with pytest.raises(InputError):
        HeightMap.load(tmp_path / "x.npz")


def test_completion_field_fills_holes_on_the_ground_and_follows_the_slope():
    """Completion surface: cells with points keep their median (a stray high point does not lift it),
    a hole inside the cloud takes the ground around it, and past the cloud's edge the surface continues
    the terrain's slope (the footprint ``cover`` reaches beyond the points)."""
    from dibrgs_core.geometry.height_map import completion_field

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 40, (40000, 2))
    ground = 0.1 * xy[:, 0]  # a slope: 1 unit up per 10 across
    box = (xy[:, 0] > 10) & (xy[:, 0] < 16) & (xy[:, 1] > 10) & (xy[:, 1] < 16)
    h = ground + np.where(box, 5.0, 0.0)
    hole = (xy[:, 0] > 25) & (xy[:, 0] < 31) & (xy[:, 1] > 25) & (xy[:, 1] < 31)
    P = np.column_stack([xy, h])[~hole]
    P = np.vstack([P, [[20.2, 20.2, 40.0]]])  # one stray match far above
    F = up_frame(np.array([0.0, 0.0, 1.0]))
    loc = lambda x, y: (F @ np.array([x, y, 0.0]))[:2]  # noqa: E731  (world -> local horizontal)
    field = completion_field(P, F, np.zeros(3), 0.5, cover=np.array([loc(-10.0, 0.0), loc(50.0, 40.0)]))
    hgt = lambda x, y: float(field.height(loc(x, y)))  # noqa: E731
    assert abs(hgt(13, 13) - 6.3) < 0.3  # the box roof
    assert abs(hgt(20.2, 20.2) - 2.02) < 0.3  # the stray point does not make a spike
    assert abs(hgt(28, 28) - 2.8) < 0.4  # the hole lies on the ground around it
    assert abs(hgt(47, 20) - 4.7) < 0.6 and abs(hgt(-7, 20) + 0.7) < 0.6  # the slope continues
    assert field.measured.any() and not field.measured.all()
    with pytest.raises(ValueError):
        completion_field(P[:2], F, np.zeros(3), 0.5)
    with pytest.raises(ValueError):
        completion_field(P, F, np.zeros(3), 0.0)
