"""Keep freed memory in the process instead of handing it back to the kernel after every tensor.

glibc serves an allocation above its mmap threshold (128 KiB to start, raised as such blocks are
freed) with a fresh mapping and trims the heap's free top above 128 KiB, so a training iteration's
image-sized temporaries (a 256x256x3 float image is 768 KiB) are mapped, zero-filled page by page
on first touch and unmapped again, every iteration. Measured on a DIBR-GS iteration at 256x256
(docs/benchmarks.md, "Freed memory kept in the process"): about 1,600 page faults and 3-4 ms of
kernel time a step; with the thresholds below, none (the step 5-7 % faster on one or two threads).

The thresholds are process-wide: set once by the ``dibrgs`` command (and the benchmarks that time
it), never by the library. A user's own ``MALLOC_MMAP_THRESHOLD_`` / ``MALLOC_TRIM_THRESHOLD_``
is left alone; other C libraries (macOS, musl, Windows) are left alone. Standard library only.
"""
from __future__ import annotations

import ctypes
import os
import platform
from typing import Mapping

#: glibc's mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: Blocks below this come from the heap and are reused (glibc's largest allowed on 64-bit: 32 MiB).
MMAP_THRESHOLD = 32 << 20
#: Free memory at the heap's top kept for the next allocation rather than returned.
TRIM_THRESHOLD = 256 << 20

_choice = "glibc defaults (keep_freed_memory was not called)"


def keep_freed_memory(environ: Mapping[str, str] = os.environ) -> str:
    """Raise glibc's mmap and trim thresholds for this process (see the module docstring); returns
    what was done and why, for the log and the report."""
    global _choice
    mine = [k for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_") if k in environ]
    if mine:
        _choice = f"the user's {' / '.join(mine)}"
    elif platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        _choice = f"the C library's defaults ({platform.system()} {platform.libc_ver()[0] or 'libc'})"
    else:
        libc = ctypes.CDLL(None)
        ok = libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
        ok = libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1 and ok
        _choice = (f"glibc keeps freed memory (mmap threshold {MMAP_THRESHOLD >> 20} MiB, trim threshold "
                   f"{TRIM_THRESHOLD >> 20} MiB)" if ok else "glibc defaults (mallopt refused the thresholds)")
    return _choice


def allocator_policy() -> str:
    """What :func:`keep_freed_memory` did in this process."""
    return _choice
