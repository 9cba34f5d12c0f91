"""What the C++ build reads from /proc/cpuinfo: the flags of its cache key and the compositing width."""
from __future__ import annotations

import pytest

from dibrgs_core.common import cpu
from dibrgs_core.render import fast


def _info(vendor: str, family: str, flags: str) -> str:
    one = f"processor\t: {{n}}\nvendor_id\t: {vendor}\ncpu family\t: {family}\nmodel\t\t: 17\nflags\t\t: {flags}\n"
    return "\n".join(one.format(n=n) for n in range(2))


ZEN4 = _info("AuthenticAMD", "25", "fpu sse2 avx avx2 fma avx512f avx512bw avx512vl")


@pytest.mark.parametrize("text,half", [
    (ZEN4, True),
    (_info("AuthenticAMD", "25", "fpu sse2 avx avx2 fma"), False),                 # Zen 3: no AVX-512
    (_info("AuthenticAMD", "26", "fpu sse2 avx avx2 fma avx512f avx512vl"), False),  # Zen 5: full width
    (_info("GenuineIntel", "6", "fpu sse2 avx avx2 fma avx512f avx512vl"), False),
    ("processor\t: 0\nFeatures\t: fp asimd sve\nCPU implementer\t: 0x41\n", False),  # arm64
    ("", False),
])
def test_half_width_avx512_only_on_zen4(text, half):
    assert cpu.half_width_avx512(text) is half


def test_flags_sorted_from_the_first_processor():
    assert cpu.cpu_flags(ZEN4) == "avx avx2 avx512bw avx512f avx512vl fma fpu sse2"
    assert cpu.cpu_flags("processor\t: 0\nFeatures\t: sve fp asimd\n") == "asimd fp sve"


@pytest.mark.parametrize("half", [True, False])
def test_default_flags_ask_for_eight_lanes_on_half_width_cpus(monkeypatch, half):
    monkeypatch.setattr(fast, "half_width_avx512", lambda: half)
    flags = fast.default_flags()
    assert ("-DDIBRGS_VBYTES=32" in flags) is half and "-fopenmp" in flags
