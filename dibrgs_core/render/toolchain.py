"""The toolchain of the C++ path (:mod:`.fast`): the compiler, the flags it is given for this CPU,
and the checks that turn a build that would fail into one clear :class:`BuildError` (a missing
compiler, ninja or Python headers, or flags the compiler rejects), each saying how to fix it.
"""
from __future__ import annotations

import logging
import os
import platform
import shlex
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path

from ..common.cpu import half_width_avx512, jcc_erratum

log = logging.getLogger("dibrgs.render")

REFERENCE_HINT = (
    "or render with the slower torch reference path (about 100x slower): set DIBRGS_RASTERIZER=reference "
    "(the dibrgs command: --rasterizer reference)"
)


class BuildError(RuntimeError):
    """The C++ rasterizer could not be built; the message says how to fix it."""

    user_error = True  # the command line prints the message, not "internal error"


def compiler() -> str:
    """The C++ compiler: ``$CXX``, default ``c++``."""
    return os.environ.get("CXX", "c++")


ALIGN_BRANCHES = "-Wa,-mbranches-within-32B-boundaries"
#: Flags that only make the build faster: a compiler that rejects one builds without it.
OPTIONAL_FLAGS = (ALIGN_BRANCHES,)


def default_flags() -> list[str]:
    """Compile flags: optimised for this CPU, OpenMP for torch's parallel_for, IEEE comparisons kept;
    8-lane compositing vectors on AVX-512 CPUs that run it at half width, and on Intel's Skylake family
    (the jump-alignment erratum) no jump across or at the end of a 32-byte block (:mod:`..common.cpu`)."""
    native = "-mcpu=native" if platform.machine().lower() in ("arm64", "aarch64") else "-march=native"
    # -fopenmp: at::parallel_for (an inline header template) runs serially without it.
    # No -ffast-math: the kernels rely on IEEE comparisons for culled lanes.
    flags = ["-O3", native, "-fopenmp", "-fno-math-errno"]
    if half_width_avx512():
        flags.append("-DDIBRGS_VBYTES=32")
    # Such a jump keeps its block out of the decoded-uop cache: the compositing forward ran 2.5 %
    # slower without the padding on a Cascade Lake (docs/benchmarks.md). An assembler without the
    # option builds without it (check_prerequisites); the cache key does not depend on that probe, so
    # a copy of the package run where no compiler is found still finds the build.
    if jcc_erratum():
        flags.append(ALIGN_BRANCHES)
    return flags


def build_flags() -> list[str]:
    """The compile flags in use: ``$DIBRGS_EXT_FLAGS`` when set, else :func:`default_flags`."""
    env = os.environ.get("DIBRGS_EXT_FLAGS")
    return shlex.split(env) if env is not None else default_flags()


def rejected_flags(cxx: str, flags: list[str], workdir: Path) -> list[str]:
    """The flags that the compiler rejects, each tried alone on a small program (OpenMP's for -fopenmp)."""
    plain, omp = workdir / "probe.cpp", workdir / "probe_omp.cpp"
    plain.write_text("int main() { return 0; }\n")
    omp.write_text("#include <omp.h>\nint main() { return omp_get_max_threads() > 0 ? 0 : 1; }\n")
    rejected = []
    for flag in flags:
        src = omp if flag == "-fopenmp" else plain
        res = subprocess.run(
            [cxx, flag, "-c", str(src), "-o", str(workdir / "probe.o")], capture_output=True, text=True, timeout=120,
            check=False,
        )
        if res.returncode != 0:
            rejected.append(flag)
    return rejected


def check_prerequisites(cxx: str, flags: list[str]) -> list[str]:
    """The flags to build with: ``flags`` less the :data:`OPTIONAL_FLAGS` that ``cxx`` rejects.
    Raises BuildError naming what is missing before starting a build that would fail."""
    if shutil.which(cxx) is None:
        raise BuildError(
            f"cannot build the C++ rasterizer: no C++ compiler found (looked for {cxx!r}"
            f"{', from $CXX' if 'CXX' in os.environ else ''}). Install one - Debian/Ubuntu: "
            "'sudo apt install g++', Fedora/RHEL: 'sudo dnf install gcc-c++', macOS: 'xcode-select --install' "
            f"(and 'brew install libomp'), conda: 'conda install gxx_linux-64' - or point CXX at one; {REFERENCE_HINT}."
        )
    try:
        from torch.utils.cpp_extension import verify_ninja_availability

        verify_ninja_availability()
    except RuntimeError:
        raise BuildError(
            f"cannot build the C++ rasterizer: the ninja build tool is missing; install it with "
            f"'{sys.executable} -m pip install ninja'; {REFERENCE_HINT}."
        ) from None
    inc = sysconfig.get_paths().get("include", "")
    if not (Path(inc) / "Python.h").is_file():
        raise BuildError(
            f"cannot build the C++ rasterizer: the Python development headers are missing ({inc}/Python.h); "
            f"install them (Debian/Ubuntu: 'sudo apt install python3-dev', Fedora: 'sudo dnf install python3-devel'); "
            f"{REFERENCE_HINT}."
        )
    with tempfile.TemporaryDirectory(prefix="dibrgs_probe_") as tmp:
        rejected = rejected_flags(cxx, flags, Path(tmp))
    dropped = [f for f in rejected if f in OPTIONAL_FLAGS]
    if dropped:
        log.info("%s does not take %s (an older assembler or compiler); building without", cxx, " ".join(dropped))
    rejected = [f for f in rejected if f not in OPTIONAL_FLAGS]
    if rejected:
        raise BuildError(
            f"cannot build the C++ rasterizer: the compiler {cxx!r} rejects the flag(s) {' '.join(rejected)} "
            f"(of {' '.join(flags)}). Use GCC >= 9 or Clang with OpenMP (libomp), e.g. CXX=g++; or set "
            f"DIBRGS_EXT_FLAGS to flags it accepts (slower without -march=native and -fopenmp); {REFERENCE_HINT}."
        )
    return [f for f in flags if f not in dropped]
