"""glibc keeps freed memory for the next allocation once the dibrgs command starts."""
from __future__ import annotations

import platform
import subprocess
import sys

import pytest

from dibrgs_core.common import allocator

# Twenty 1 MiB blocks written and freed, ten times over: the pattern of a training iteration's
# image-sized temporaries. Prints the minor page faults of the ten rounds.
ROUNDS = r"""
import ctypes, resource, sys
if sys.argv[1] == "command":  # what the dibrgs command sets at start, before any work
    from dibrgs_core import cli
    assert cli.main(["info", "/no/such/scene"]) != 0
libc = ctypes.CDLL(None)
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
def one_round():
    blocks = [libc.malloc(1 << 20) for _ in range(20)]
    for b in blocks:
        ctypes.memset(b, 1, 1 << 20)
    for b in blocks:
        libc.free(b)
one_round(); one_round()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    one_round()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def faults(mode: str) -> int:
    out = subprocess.run([sys.executable, "-c", ROUNDS, mode], capture_output=True, text=True, check=True)
    return int(out.stdout.split()[-1])


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_freed_blocks_are_reused_without_page_faults():
    pages = 10 * 20 * (1 << 20) // 4096
    kept = faults("command")
    assert kept < pages // 100, f"{kept} page faults for {pages} pages written with the thresholds raised"
    # glibc's defaults hand the freed heap top back and fault every page in again; if a future
    # glibc stopped doing so, this test would no longer show what the setting is for.
    assert faults("default") > pages // 2


def test_the_users_own_thresholds_are_left_alone():
    assert "the user's MALLOC_TRIM_THRESHOLD_" in allocator.keep_freed_memory({"MALLOC_TRIM_THRESHOLD_": "0"})
    assert allocator.allocator_policy().startswith("the user's")
