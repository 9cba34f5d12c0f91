"""This CPU as ``/proc/cpuinfo`` describes it (Linux; the platform's names elsewhere), standard library
only: its fields (the benchmarks' machine line), its instruction-set flags (part of the C++ build's
cache key), the vector width the compositing kernels run fastest at, and whether the build should
keep jumps off 32-byte boundaries (Intel's Skylake family).

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


# Intel cores of the Skylake family (family 6: Skylake client and server, Cascade and Cooper Lake,
# Kaby, Coffee, Whiskey, Amber and Comet Lake): with the microcode for their "jump conditional code"
# erratum, a jump that crosses or ends on a 32-byte boundary keeps its 32 bytes out of the decoded
# micro-op cache, so a hot loop holding one is decoded again on every pass.
JCC_ERRATUM_MODELS = frozenset({0x4E, 0x55, 0x5E, 0x8E, 0x9E, 0xA5, 0xA6})


def jcc_erratum(text: str | None = None) -> bool:
    """Whether this CPU is one of Intel's Skylake-family cores with the jump-alignment erratum."""
    text = cpuinfo() if text is None else text
    try:
        model = int(cpuinfo_field(text, "model"))
    except ValueError:
        return False
    return (cpuinfo_field(text, "vendor_id") == "GenuineIntel" and cpuinfo_field(text, "cpu family") == "6"
            and model in JCC_ERRATUM_MODELS)


def half_width_avx512(text: str | None = None) -> bool:
    """Whether this CPU has AVX-512 but runs 512-bit operations as two 256-bit halves (AMD Zen 4)."""
    text = cpuinfo() if text is None else text
    return (cpuinfo_field(text, "vendor_id") == "AuthenticAMD" and cpuinfo_field(text, "cpu family") == "25"
            and "avx512f" in cpuinfo_field(text, "flags").split())
