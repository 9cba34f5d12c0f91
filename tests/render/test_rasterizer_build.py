"""The C++ rasterizer's build: failures are errors that say how to fix them, the
reference backend is an explicit choice that needs no compiler, the cache is
keyed by content (two copies of the package share one build), and the AVX2 and
AVX-512 kernels compile without stack spills in their hot loops."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from dibrgs_core import render
from dibrgs_core.render import fast

REPO = Path(__file__).resolve().parents[2]
CSRC = REPO / "dibrgs_core" / "render" / "csrc"

RENDER = (
    "import torch\n"
    "from dibrgs_core.render import rasterize\n"
    "img, a, d, m = rasterize(torch.tensor([[0., 0., 3.]]), torch.tensor([[1., 0, 0, 0]]), torch.full((1, 3), .2),"
    " torch.tensor([.5]), torch.ones(1, 3), torch.eye(4), torch.tensor([[20., 0, 8], [0, 20., 8], [0, 0, 1]]),"
    " 16, 16)\n"
    "print('alpha', float(a.max()))\n"
)


def run_python(code: str, cwd: Path = REPO, **env: str) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items() if k not in ("DIBRGS_RASTERIZER", "DIBRGS_EXT_FLAGS", "CXX")}
    return subprocess.run(
        [sys.executable, "-c", code], env={**base, **env}, cwd=cwd, capture_output=True, text=True, timeout=600,
        check=False,
    )


def test_missing_compiler_is_an_error_that_says_how_to_fix(tmp_path):
    """No compiler: rendering raises BuildError naming the compiler, the package to install
    and the explicit reference switch; nothing falls back silently."""
    code = "from dibrgs_core.render import fast\nprint('built', fast.is_built())\n" + RENDER
    res = run_python(code, CXX=str(tmp_path / "no-such-compiler"), DIBRGS_EXT_DIR=str(tmp_path / "ext"))
    assert res.returncode != 0
    assert "built False" in res.stdout and "alpha" not in res.stdout
    err = res.stderr
    assert "BuildError" in err and "no C++ compiler found" in err and "no-such-compiler" in err
    assert "apt install g++" in err and "DIBRGS_RASTERIZER=reference" in err


@pytest.mark.slow
def test_reference_backend_needs_no_compiler(tmp_path):
    """DIBRGS_RASTERIZER=reference or set_backend("reference") renders without trying a build."""
    env = {"CXX": str(tmp_path / "no-such-compiler"), "DIBRGS_EXT_DIR": str(tmp_path / "ext")}
    res = run_python(RENDER, DIBRGS_RASTERIZER="reference", **env)
    assert res.returncode == 0, res.stderr
    assert float(res.stdout.split()[-1]) > 0.4
    res = run_python("from dibrgs_core import render\nrender.set_backend('reference')\n" + RENDER, **env)
    assert res.returncode == 0, res.stderr
    assert float(res.stdout.split()[-1]) > 0.4
    assert not (tmp_path / "ext").exists()  # no build was attempted


@pytest.mark.skipif(shutil.which(os.environ.get("CXX", "c++")) is None, reason="no C++ compiler")
def test_rejected_flags_are_named(tmp_path):
    """Flags the real compiler rejects are named in the error, the accepted ones are not."""
    res = run_python(
        RENDER, DIBRGS_EXT_FLAGS="-O2 -fno-such-flag-dibrgs", DIBRGS_EXT_DIR=str(tmp_path / "ext"),
        DIBRGS_RASTERIZER="fast",
    )
    assert res.returncode != 0
    assert "rejects the flag(s) -fno-such-flag-dibrgs (of -O2 -fno-such-flag-dibrgs)" in res.stderr
    assert "DIBRGS_EXT_FLAGS" in res.stderr and "DIBRGS_RASTERIZER=reference" in res.stderr


def test_backend_setting_and_environment(monkeypatch):
    monkeypatch.delenv("DIBRGS_RASTERIZER", raising=False)
    assert render.get_backend() == "auto"
    monkeypatch.setenv("DIBRGS_RASTERIZER", "reference")
    assert render.get_backend() == "reference"
    try:
        render.set_backend("fast")
        assert render.get_backend() == "fast"
        with pytest.raises(ValueError, match="set_backend: unknown rasterizer backend 'gpu'"):
            render.set_backend("gpu")  # type: ignore[arg-type]
    finally:
        render.set_backend(None)
    assert render.get_backend() == "reference"
    monkeypatch.setenv("DIBRGS_RASTERIZER", "cuda")
    with pytest.raises(ValueError, match=r"\$DIBRGS_RASTERIZER: unknown rasterizer backend 'cuda'"):
        render.get_backend()


def test_cache_key_follows_flags_not_location(monkeypatch):
    d = fast.build_dir()
    monkeypatch.setenv("DIBRGS_EXT_FLAGS", "-O2")
    assert fast.build_dir() != d and fast.build_dir().parent == d.parent
    monkeypatch.delenv("DIBRGS_EXT_FLAGS")
    assert fast.build_dir() == d
    assert str(REPO) not in d.name


def _copy_package(dst: Path) -> None:
    (dst / "dibrgs_core").mkdir(parents=True)
    shutil.copy(REPO / "dibrgs_core" / "__init__.py", dst / "dibrgs_core" / "__init__.py")
    for sub in ("render", "common"):  # render imports common (cpu flags)
        shutil.copytree(REPO / "dibrgs_core" / sub, dst / "dibrgs_core" / sub,
                        ignore=shutil.ignore_patterns("__pycache__"))


@pytest.mark.slow
@pytest.mark.skipif(shutil.which(os.environ.get("CXX", "c++")) is None, reason="no C++ compiler")
def test_two_copies_share_one_fresh_build(tmp_path):
    """Two copies of the package in different folders (a checkout and an installed add-on)
    resolve to one cache folder: the first compiles it from scratch (announcing the compile
    through on_start), the second loads it with no compiler at all and does not rebuild. Built
    unoptimised ($DIBRGS_EXT_FLAGS, part of the cache key like any flags): 50 s instead of 80-90 s
    of this suite, and what is shared does not depend on the flags."""
    for name in ("a", "b"):
        _copy_package(tmp_path / name)
    ext = str(tmp_path / "ext")
    flags = "-O0 -fopenmp"
    report = (
        "import json, os, dibrgs_core\n"
        "from dibrgs_core.render import fast\n"
        "before = fast.is_built()\n"
        "msgs = []\n"
        "m = fast.build(on_start=msgs.append)\n"
        "print(json.dumps(dict(pkg=dibrgs_core.__file__, dir=str(fast.build_dir()), so=m.__file__,"
        " mtime=os.stat(m.__file__).st_mtime_ns, before=before, msgs=msgs, after=fast.is_built())))\n"
    )
    res = run_python(report, cwd=tmp_path / "a", PYTHONPATH=str(tmp_path / "a"), DIBRGS_EXT_DIR=ext,
                     DIBRGS_EXT_FLAGS=flags)
    assert res.returncode == 0, res.stderr
    a = json.loads(res.stdout.strip().splitlines()[-1])
    assert a["pkg"].startswith(str(tmp_path / "a"))
    assert not a["before"] and a["after"] and len(a["msgs"]) == 1 and "compiling the C++ rasterizer" in a["msgs"][0]
    assert "compiling the C++ rasterizer" in res.stderr  # the log line

    # No compiler on PATH for the second copy (CXX itself is part of the cache key, so it stays unset).
    (tmp_path / "empty-bin").mkdir()
    res = run_python(report + RENDER, cwd=tmp_path / "b", PYTHONPATH=str(tmp_path / "b"), DIBRGS_EXT_DIR=ext,
                     DIBRGS_EXT_FLAGS=flags, PATH=str(tmp_path / "empty-bin"))
    assert res.returncode == 0, res.stderr
    b = json.loads([ln for ln in res.stdout.splitlines() if ln.startswith("{")][-1])
    assert b["pkg"].startswith(str(tmp_path / "b"))
    assert b["before"] and b["msgs"] == [] and (b["dir"], b["so"], b["mtime"]) == (a["dir"], a["so"], a["mtime"])
    assert float(res.stdout.split()[-1]) > 0.4
    ninja = (Path(a["dir"]) / "build.ninja").read_text()
    assert str(tmp_path / "a") not in ninja and str(tmp_path / "b") not in ninja


KERNELS = """#include "composite.h"
using namespace dibrgs;
template void dibrgs::forward_tile<float, 5, false>(const Scene<float>&, int64_t, Workspace<float>&, const Planes<float>&,
                                                    float*, int32_t*, Stats*);
template void dibrgs::backward_tile<float, 5, false>(const Scene<float>&, int64_t, Workspace<float>&,
                                                     const Planes<const float>&, const float*, const int32_t*, float*,
                                                     Stats*);
template void dibrgs::forward_tile<float, 0, false>(const Scene<float>&, int64_t, Workspace<float>&, const Planes<float>&,
                                                    float*, int32_t*, Stats*);
template void dibrgs::backward_tile<float, 0, false>(const Scene<float>&, int64_t, Workspace<float>&,
                                                     const Planes<const float>&, const float*, const int32_t*, float*,
                                                     Stats*);
"""
DOUBLE = KERNELS.replace("float", "double")


def _hot_ranges() -> list[tuple[int, int]]:
    """Line ranges of composite.h between '// [hot]' and '// [/hot]' (the per-vector loops)."""
    ranges, start = [], None
    for i, line in enumerate((CSRC / "composite.h").read_text().splitlines(), 1):
        if "// [hot]" in line:
            start = i
        elif "// [/hot]" in line:
            ranges.append((start, i))
    assert len(ranges) >= 4
    return ranges


@pytest.mark.skipif(shutil.which("g++") is None or shutil.which("objdump") is None, reason="needs g++ and objdump")
@pytest.mark.parametrize("march,reg,lanes,defines", [
    ("skylake-avx512", "zmm", 16, []), ("haswell", "ymm", 8, []),
    pytest.param("skylake-avx512", "ymm", 8, ["-DDIBRGS_VBYTES=32"], marks=pytest.mark.slow),
    pytest.param("x86-64", "xmm", 4, [], marks=pytest.mark.slow)])
def test_kernels_compile_for_each_vector_width(tmp_path, march, reg, lanes, defines):
    """The kernels compile for AVX-512 (zmm, 16 float lanes), AVX2 (ymm, 8) and plain SSE2
    (xmm, 4) whatever this machine runs, and for AVX-512 at the AVX2 width when a build asks for
    it (``-DDIBRGS_VBYTES=32``: no zmm at all); on the AVX2 and AVX-512 targets the float
    kernels' hot loops (marked in composite.h) have no vector operand on the stack: no spills."""
    src = tmp_path / "k.cpp"
    src.write_text(KERNELS + DOUBLE)
    obj = tmp_path / "k.o"
    subprocess.run(["g++", "-O3", "-g", f"-march={march}", *defines, "-std=c++17", f"-I{CSRC}", "-c", str(src), "-o",
                    str(obj)], check=True, capture_output=True, text=True, timeout=300)
    asm = subprocess.run(["objdump", "-d", "-l", "--no-show-raw-insn", "-C", str(obj)],
                         capture_output=True, text=True, check=True).stdout
    assert re.search(rf"%{reg}\d", asm)
    for wider in {"zmm": [], "ymm": ["zmm"], "xmm": ["ymm", "zmm"]}[reg]:
        assert f"%{wider}" not in asm, f"{march} uses {wider}"
    ranges = _hot_ranges()
    fn, loc, hot, spills, frame = "", None, 0, [], r"%rsp"
    for line in asm.splitlines():
        if m := re.match(r"^[0-9a-f]+ <(.*)>:$", line):
            fn, frame = m.group(1), r"%rsp"
        elif re.search(r"\bmov\s+%rsp,%rbp", line):
            frame = r"%rsp|%rbp"  # rbp is this function's frame pointer
        elif m := re.match(r"^/\S*composite\.h:(\d+)", line):
            loc = int(m.group(1))
        elif line.startswith("/"):
            loc = None
        elif loc and "<float" in fn and re.match(r"^\s+[0-9a-f]+:\s", line) and any(a < loc < b for a, b in ranges):
            hot += 1
            if re.search(rf"\(({frame})\)", line) and re.search(r"%[xyz]mm", line):
                spills.append(f"composite.h:{loc}: {line.strip()}")
    assert hot > 200
    if reg != "xmm":  # SSE2 (16 four-lane registers) is a fallback, not a target
        assert not spills, "\n".join(spills[:10])
    # The lane count the header chooses for this target.
    probe = tmp_path / "lanes.cpp"
    probe.write_text(f'#include "composite.h"\nstatic_assert(dibrgs::Geo<float>::L == {lanes}, "lanes");\n')
    subprocess.run(["g++", f"-march={march}", *defines, "-std=c++17", f"-I{CSRC}", "-fsyntax-only", str(probe)],
                   check=True, timeout=120)


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++")
def test_extension_source_compiles_for_avx512():
    """The whole extension source (torch glue included) passes the compiler's checks for an
    AVX-512 target (-fsyntax-only: this machine need not run it)."""
    import sysconfig

    import torch

    inc = Path(torch.__file__).parent / "include"
    cmd = ["g++", "-std=c++17", "-fsyntax-only", "-march=skylake-avx512", "-fopenmp", "-DTORCH_EXTENSION_NAME=x",
           "-DTORCH_API_INCLUDE_EXTENSION_H", "-isystem", str(inc), "-isystem", str(inc / "torch/csrc/api/include"),
           "-isystem", sysconfig.get_paths()["include"], str(CSRC / "rasterize.cpp")]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600, check=False)
    assert res.returncode == 0, res.stderr[-3000:]


EXP = r"""#include <cstdio>
#include "composite.h"
using namespace dibrgs;
int main() {
  const int L = VBYTES / 4;
  double worst = 0, below = 0;
  long bad = 0;
  for (long i = 0; i <= 1500000; i += L) {  // t from -150 to 0 in steps of 1e-4
    VF t;
    for (int l = 0; l < L; ++l) t[l] = -150.0f + 1e-4f * float(i + l);
    const VF e = Exp<float>::eval(t, VF{});
    for (int l = 0; l < L; ++l) {
      const double x = t[l], v = e[l];
      if (x > 0) continue;  // above hi: the AVX2 path clamps, AVX-512's need not
      if (!(v == v) && x >= Exp<float>::tlow) ++bad;  // NaN where a value is due
      if (x >= Exp<float>::tlow) worst = std::max(worst, std::fabs(v / std::exp2(x) - 1.0));
      else if (v > below) below = v;
    }
  }
  std::printf("%ld %.3g %.3g\n", bad, worst, below);
  return 0;
}
"""


@pytest.mark.skipif(shutil.which("g++") is None, reason="needs g++")
@pytest.mark.parametrize("march", ["native", pytest.param("haswell", marks=pytest.mark.slow)])
def test_kernels_exponential_is_accurate(tmp_path, march):
    """The kernels' 2^t (AVX-512: vreduceps and scalef; AVX2 and others: rounding by adding
    1.5 2^23): relative error under 2e-7 from tlow (-125) to 0, and below 2^(tlow + 1) under tlow
    (a culled lane), on this machine's code path and on the AVX2 one (where this CPU runs it)."""
    if march == "haswell" and "avx2" not in fast.cpu_flags().split():
        pytest.skip("this CPU has no AVX2")
    src, exe = tmp_path / "exp.cpp", tmp_path / "exp"
    src.write_text(EXP)
    subprocess.run(["g++", "-O2", f"-march={march}", "-std=c++17", f"-I{CSRC}", str(src), "-o", str(exe)], check=True,
                   capture_output=True, text=True, timeout=300)
    bad, worst, below = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout.split()
    assert int(bad) == 0
    assert float(worst) < 2e-7
    assert float(below) < 2.0 ** -124
