"""This CPU as ``/proc/cpuinfo`` describes it (Linux; the platform's names elsewhere), standard library
only: its fields (the benchmarks' machine line), its instruction-set flags (part of the C++ build's
cache key) and the vector width the compositing kernels run fastest at.

AMD Zen 4 (vendor AuthenticAMD, family 25, with AVX-512) executes a 512-bit operation as two
256-bit halves, so 16-lane vectors do the work of two 8-lane ones while a tile row's Gaussians
leave more of their lanes empty (41 % of evaluated lanes composite a pair at 16 lanes, 57 % at
8): at 512x512 its compositing forward plus backward took 80.6 ms at 16 lanes and 66.0 ms at 8
(docs/benchmarks.md, "Vector width on AMD Zen 4"). Intel's AVX-512 cores and Zen 5 (family 26)
keep the native 16 lanes.
"""
from __future__ import annotations

import platform
from pathlib import Path


def cpuinfo() -> str:
    """The text of ``/proc/cpuinfo`` ("" where there is none)."""
    try:
        return Path("/proc/cpuinfo").read_text()
    except OSError:
        return ""


def cpuinfo_field(text: str, *names: str) -> str:
    """The first processor's value of the first field named one of ``names``."""
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() in names:
            return value.strip()
    return ""


def cpu_flags(text: str | None = None) -> str:
    """The instruction-set flags, sorted and space-separated (the processor's name without them)."""
    text = cpuinfo() if text is None else text
    flags = cpuinfo_field(text, "flags", "Features")
    return " ".join(sorted(flags.split())) if flags else (platform.processor() or platform.machine())


def half_width_avx512(text: str | None = None) -> bool:
    """Whether this CPU has AVX-512 but runs 512-bit operations as two 256-bit halves (AMD Zen 4)."""
    text = cpuinfo() if text is None else text
    return (cpuinfo_field(text, "vendor_id") == "AuthenticAMD" and cpuinfo_field(text, "cpu family") == "25"
            and "avx512f" in cpuinfo_field(text, "flags").split())
