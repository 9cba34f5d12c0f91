"""Source views of multi-view stereo: the neighbours that see a view's ground, not every view."""
from __future__ import annotations

import numpy as np
from geom_synth import nadir

from dibrgs_core.geometry.view_selection import angle_weight, select_sources


def ground_points(n: int = 2000, half: float = 300.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-half, half, (n, 2)), rng.normal(0, 1, n)]


def test_few_views_are_all_matched_in_their_order():
    cams = [nadir(20.0 * i) for i in range(5)]
    ranges = [(50.0, 200.0)] * 5
    assert select_sources(cams, ground_points(), ranges, 8) == [[j for j in range(5) if j != i] for i in range(5)]
    assert select_sources(cams, ground_points(), ranges, 0) == [[j for j in range(5) if j != i] for i in range(5)]


def test_a_long_strip_matches_its_neighbours_not_the_far_photos():
    """A corridor of 30 photos 20 units apart at 100 units height (footprint about 115): each photo
    is matched against the photos beside it, never against one that does not see its ground."""
    cams = [nadir(20.0 * i, name=f"{i:03d}") for i in range(30)]
    ranges = [(50.0, 200.0)] * 30
    for pts in (ground_points(), None):  # from SfM points, and from the depth range alone
        src = select_sources(cams, pts, ranges, 4)
        for i, s in enumerate(src):
            assert 1 <= len(s) <= 4
            assert all(abs(j - i) <= 5 for j in s), (i, s)  # 100 units apart or less: overlapping ground
            assert min(abs(j - i) for j in s) == 1, (i, s)  # a direct neighbour is among them
        assert sorted(src[15]) == [13, 14, 16, 17]


def test_the_same_viewpoint_twice_is_no_source():
    """A second photo from the same place (a hover, a duplicated frame) gives no depth: skipped
    for one that does, though it overlaps completely."""
    cams = [nadir(0.0), nadir(0.0, name="again"), nadir(25.0), nadir(-25.0), nadir(200.0), nadir(260.0)]
    src = select_sources(cams, ground_points(), [(50.0, 200.0)] * len(cams), 2)
    assert sorted(src[0]) == [2, 3]
    assert 1 not in src[0] and 0 not in src[1]


def test_no_overlap_falls_back_to_the_nearest_cameras():
    """Photos that see nothing of each other's ground (a gap in the survey) still get sources."""
    cams = [nadir(1000.0 * i) for i in range(6)]
    src = select_sources(cams, None, [(50.0, 200.0)] * 6, 2)
    assert src[0] == [1, 2] and sorted(src[3]) == [2, 4]


def test_angle_prior_peaks_at_five_degrees_and_scales_free():
    w = angle_weight(np.array([0.5, 3.0, 5.0, 15.0, 45.0]), 1.0)
    assert w[0] == 0 and w[2] == 1.0 and w[1] < w[3] < w[2] and w[4] < w[3]
    # The same survey in millimetres picks the same sources.
    cams = [nadir(20.0 * i) for i in range(12)]
    mm = [nadir(20000.0 * i, height=1e5) for i in range(12)]
    pts = ground_points()
    assert (select_sources(cams, pts, [(50.0, 200.0)] * 12, 3)
            == select_sources(mm, pts * 1000, [(5e4, 2e5)] * 12, 3))
