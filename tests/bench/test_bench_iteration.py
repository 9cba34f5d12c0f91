"""scripts/bench_iteration.py's two-thread ratio: which rounds count as calm, and a real run of it."""
from __future__ import annotations

import importlib.util

import pytest
import torch

from paths import REPO


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_iteration", REPO / "scripts" / "bench_iteration.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_calm_rounds_are_those_whose_every_control_was_near_its_best(bench):
    # one thread before / after, two threads before / after; bests 10.0 and 5.0
    controls = [[10.0, 10.5, 5.0, 5.2],   # calm
                [10.2, 13.0, 5.1, 5.0],   # one-thread side slowed after its timing
                [10.0, 10.0, 5.0, 9.0],   # two-thread side slowed
                [11.0, 10.9, 5.4, 5.5]]   # within 10 % everywhere
    assert bench.calm_rounds(controls) == [0, 3]
    assert bench.calm_rounds(controls, slack=1.5) == [0, 1, 3]
    assert bench.calm_rounds(controls, slack=1.0) == []


def test_thread_ratio_times_both_sides_and_brackets_them_with_controls(bench):
    x = torch.rand(1 << 16)
    before = torch.get_num_threads()
    try:
        res = bench.thread_ratio(lambda: torch.exp(x).sum(), n_views=1, threads=2, rounds=3, repeats=2)
    finally:
        torch.set_num_threads(before)
    assert len(res["ratios"]) == len(res["control_ms"]) == 3
    assert all(len(c) == 4 and min(c) > 0 for c in res["control_ms"])
    assert res["calm_rounds"] == bench.calm_rounds(res["control_ms"])
    if res["calm_rounds"]:  # none when the host was busy in every round
        calm = sorted(res["ratios"][i] for i in res["calm_rounds"])
        assert calm[0] <= res["calm_median_ratio"] <= calm[-1]
    assert res["control_ratio"] > 0
    assert res["ratio_of_minima"] == min(res["many_ms"]) / min(res["one_ms"])
