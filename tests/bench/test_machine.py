"""The machine line of the benchmarks (dibrgs_core/bench/machine.py) against /proc/cpuinfo."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from dibrgs_core.bench import pages
from dibrgs_core.bench.machine import cpu


def test_cpu_names_the_model_cores_vector_extensions_and_load():
    c = cpu()
    assert c["model"] and c["cores"] == os.cpu_count()
    assert len(c["load"]) == 3 and all(x >= 0 for x in c["load"])
    info = Path("/proc/cpuinfo")
    if not info.exists():
        pytest.skip("no /proc/cpuinfo")
    flags = next(line.split(":", 1)[1].split() for line in info.read_text().splitlines() if line.startswith("flags"))
    vec = c["vector"].split()
    assert set(vec) <= set(flags)  # only the CPU's own flags
    assert all(f in ("sse4_2", "avx", "avx2", "fma") or f.startswith("avx512") for f in vec)
    for f in ("avx2", "fma", "avx512f"):  # the ones the kernels' width depends on, when present
        assert (f in vec) == (f in flags)
    assert c["model"] in pages.machine_description()
