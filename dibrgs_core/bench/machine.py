"""The machine a benchmark ran on, as benchmarks.md records it: CPU model, its vector extensions,
core count and load average (from /proc/cpuinfo on Linux; the platform's names elsewhere)."""
from __future__ import annotations

import os
import platform
import re

from ..common.cpu import cpuinfo, cpuinfo_field


def cpu() -> dict:
    """``{"model", "cores", "vector", "load"}``: the CPU's model name, ``os.cpu_count()``, the
    vector extensions the kernels care about (space-separated ``/proc/cpuinfo`` flags: sse4_2, avx,
    avx2, fma, avx512*) and the 1/5/15-minute load averages."""
    text = cpuinfo()
    model = cpuinfo_field(text, "model name") or platform.processor() or platform.machine()
    flags = cpuinfo_field(text, "flags").split()
    vec = [f for f in flags if re.fullmatch(r"sse4_2|avx|avx2|fma|avx512\w*", f)]
    return {"model": model, "cores": os.cpu_count(), "vector": " ".join(vec), "load": os.getloadavg()}
