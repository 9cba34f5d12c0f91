"""The machine a benchmark ran on, as benchmarks.md records it: CPU model, its vector extensions,
core count and load average (from /proc/cpuinfo on Linux; the platform's names elsewhere)."""
from __future__ import annotations

import os
import platform
import re
from pathlib import Path


def cpu() -> dict:
    """``{"model", "cores", "vector", "load"}``: the CPU's model name, ``os.cpu_count()``, the
    vector extensions the kernels care about (space-separated ``/proc/cpuinfo`` flags: sse4_2, avx,
    avx2, fma, avx512*) and the 1/5/15-minute load averages."""
    model, flags = "", []
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and not model:
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags") and not flags:
                flags = line.split(":", 1)[1].split()
    except OSError:
        pass
    model = model or platform.processor() or platform.machine()
    vec = [f for f in flags if re.fullmatch(r"sse4_2|avx|avx2|fma|avx512\w*", f)]
    return {"model": model, "cores": os.cpu_count(), "vector": " ".join(vec), "load": os.getloadavg()}
