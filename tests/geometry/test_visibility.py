"""Training-view visibility of held-out pixels and the error split by it (dibrgs_core.geometry.visibility)."""
from __future__ import annotations

import numpy as np
import pytest

from dibrgs_core.data.levir import read_scene
from dibrgs_core.geometry.visibility import SplitError, visibility_count


@pytest.fixture(scope="module")
def scene(tiny_scene):
    return read_scene(tiny_scene)


def test_a_view_sees_itself_and_an_occluder_hides_everything(scene):
    v = scene.train_views()[0]
    ok = v.depth > 0
    assert ok.all()
    # Its own depth: every pixel lands on itself, in front by 0 % -> seen once.
    assert (visibility_count(v.camera, v.depth, [(v.camera, v.depth)]) == 1).all()
    # Something at half the depth in front of every pixel hides it.
    assert (visibility_count(v.camera, v.depth, [(v.camera, v.depth * 0.5)]) == 0).all()
    # A source with no surface anywhere (sky) cannot occlude.
    assert (visibility_count(v.camera, v.depth, [(v.camera, np.zeros_like(v.depth))]) == 1).all()
    # Where its photo holds no data it sees nothing (None: every pixel holds data).
    half = np.zeros_like(ok)
    half[:, : ok.shape[1] // 2] = True
    assert np.array_equal(visibility_count(v.camera, v.depth, [(v.camera, v.depth, half)]), half.astype(np.int32))
    assert (visibility_count(v.camera, v.depth, [(v.camera, v.depth, None)]) == 1).all()
    # No surface in the target (0, NaN, inf) is marked -1 and never raises.
    d = v.depth.copy()
    d[0, 0], d[0, 1], d[0, 2] = 0.0, np.nan, np.inf
    c = visibility_count(v.camera, d, [(v.camera, v.depth)])
    assert (c[0, :3] == -1).all() and (c[1:] == 1).all()
    with pytest.raises(ValueError, match="depth of"):
        visibility_count(v.camera, d[:-1], [(v.camera, v.depth)])


def test_held_out_views_of_the_orbit_split_into_all_groups(scene):
    sources = [(v.camera, v.depth) for v in scene.train_views()]
    counts = np.stack([visibility_count(v.camera, v.depth, sources) for v in scene.test_views()])
    assert counts.min() >= 0 and counts.max() <= len(sources)
    frac = [np.mean(counts == 0), np.mean(counts == 1), np.mean(counts >= 2)]
    # Three views of an orbit over a city: most pixels are seen twice or more, but
    # streets hidden behind buildings and the image borders leave some to one or none.
    assert all(f > 0.005 for f in frac), frac
    assert frac[2] > 0.4, frac
    # A looser occlusion tolerance can only see more.
    loose = np.stack([visibility_count(v.camera, v.depth, sources, rel_tol=0.2) for v in scene.test_views()])
    assert (loose >= counts).all() and (loose > counts).any()


def test_split_error_gives_exact_psnr_per_group():
    gt = np.full((4, 5, 3), 0.5)
    count = np.array([[0] * 5, [1] * 5, [2] * 5, [3] * 5])
    render = gt.copy()
    render[1] += 0.1          # only the "one" group is off, by 0.1 -> 20 dB
    render[3] -= 0.01         # three views: 40 dB; pooled with row 2 (exact) -> 43.01 dB
    acc = SplitError.empty()
    view = acc.add(render, gt, count)
    assert view == pytest.approx(-10 * np.log10((5 * 0.01 + 5 * 1e-4) / 20))  # this view, whole image
    p = acc.psnr()
    assert p["one"] == pytest.approx(20.0)
    assert p["two_plus"] == pytest.approx(40.0 + 10 * np.log10(2))
    assert p["unseen"] > 150  # exact: finite despite zero error
    assert p["all"] == pytest.approx(-10 * np.log10((5 * 0.01 + 5 * 1e-4) / 20))
    assert acc.fractions() == {"all": 1.0, "unseen": 0.25, "one": 0.25, "two_plus": 0.5}
    # Seen pixels pool rows 1-3 (the unseen row 0 is exact too, so it would not move "all"'s sum).
    assert acc.seen_psnr() == pytest.approx(-10 * np.log10((5 * 0.01 + 5 * 1e-4) / 15))
    assert SplitError.empty().psnr()["one"] is None and SplitError.empty().seen_psnr() is None
