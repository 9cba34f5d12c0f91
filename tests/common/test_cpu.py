"""What the C++ build reads from /proc/cpuinfo: the flags of its cache key and the compositing width."""
from __future__ import annotations

import shutil

import pytest

from dibrgs_core.common import cpu
from dibrgs_core.render import toolchain


def _info(vendor: str, family: str, flags: str, model: int = 17) -> str:
    one = (f"processor\t: {{n}}\nvendor_id\t: {vendor}\ncpu family\t: {family}\nmodel\t\t: {model}\n"
           f"model name\t: x\nflags\t\t: {flags}\n")
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
    monkeypatch.setattr(toolchain, "half_width_avx512", lambda: half)
    flags = toolchain.default_flags()
    assert ("-DDIBRGS_VBYTES=32" in flags) is half and "-fopenmp" in flags


AVX512 = "fpu sse2 avx avx2 fma avx512f avx512dq avx512vl"


@pytest.mark.parametrize("text,affected", [
    (_info("GenuineIntel", "6", AVX512, model=85), True),    # Skylake-SP / Cascade Lake
    (_info("GenuineIntel", "6", "avx avx2 fma", model=158), True),  # Coffee Lake
    (_info("GenuineIntel", "6", AVX512, model=106), False),  # Ice Lake-SP
    (_info("GenuineIntel", "6", AVX512, model=143), False),  # Sapphire Rapids
    (_info("AuthenticAMD", "23", "avx avx2 fma", model=85), False),
    ("processor\t: 0\nFeatures\t: fp asimd sve\nCPU implementer\t: 0x41\n", False),
    ("", False),
])
def test_jcc_erratum_only_on_the_skylake_family(text, affected):
    assert cpu.jcc_erratum(text) is affected


@pytest.mark.parametrize("affected", [True, False])
def test_default_flags_align_branches_on_affected_cpus(monkeypatch, affected):
    """The key's flags follow the CPU alone (not whether a compiler is found): a build made with a
    compiler is found again without one."""
    monkeypatch.setattr(toolchain, "jcc_erratum", lambda: affected)
    monkeypatch.setenv("CXX", "/nonexistent/c++")
    assert (toolchain.ALIGN_BRANCHES in toolchain.default_flags()) is affected
    with pytest.raises(toolchain.BuildError, match="no C\\+\\+ compiler"):  # never probed without one
        toolchain.check_prerequisites("/nonexistent/c++", toolchain.default_flags())


@pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++")
def test_gnu_assembler_takes_the_branch_alignment(tmp_path):
    assert toolchain.rejected_flags("g++", [toolchain.ALIGN_BRANCHES], tmp_path) == []


@pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++")
def test_an_assembler_without_branch_alignment_is_detected(tmp_path):
    """An older toolchain (GNU as < 2.34) rejects the option: the probe says so, and the build's
    checks leave it out instead of failing."""
    cc = tmp_path / "old-c++"
    cc.write_text('#!/bin/sh\nfor a in "$@"; do [ "$a" = "-Wa,-mbranches-within-32B-boundaries" ] && exit 1; done\n'
                  'exec g++ "$@"\n')
    cc.chmod(0o755)
    assert toolchain.rejected_flags(str(cc), [toolchain.ALIGN_BRANCHES], tmp_path) == [toolchain.ALIGN_BRANCHES]
    assert toolchain.check_prerequisites(str(cc), ["-O2", toolchain.ALIGN_BRANCHES]) == ["-O2"]
