"""MKL's vector maths functions initialised on one thread, so that results do not vary by process.

Torch's CPU build computes ``tanh``, ``exp``, ``log``, ``sqrt``, ``sin``, ``cos`` and a few more of
float tensors through MKL's vector maths library (VML), a chunk a thread. MKL picks its
implementation of each function on the function's first call. When that first call comes from two
threads at once, the first thread's chunk is sometimes computed by another implementation: found
in the decoder's ``tanh`` (``models/decoder.py``), where the first view rendered in about one
process in fifteen differed from every later render of the same view in rows 0-112 of 225 (the
first thread's half) by up to 8e-6, so two scripts scoring the same run disagreed in the sixth
decimal of a PSNR. A call on a tensor smaller than torch's grain size runs on one thread; after it
every process computes the same values (0 of 100 processes differed, 4 of 60 without).
"""
from __future__ import annotations

import torch

# The operators torch routes through VML for float and double tensors (ATen/cpu/vml.h).
_OPS = (torch.acos, torch.asin, torch.atan, torch.cos, torch.erf, torch.erfc, torch.erfinv, torch.exp,
        torch.log, torch.log10, torch.log2, torch.sin, torch.sqrt, torch.tan, torch.tanh, torch.trunc)


def init_vml() -> None:
    """Call each VML-backed operator once on one thread (about 5 ms; once a process, at import of
    :mod:`dibrgs_core.render`)."""
    for dt in (torch.float32, torch.float64):
        x = torch.linspace(0.1, 0.9, 64, dtype=dt)  # far below torch's grain size of 2048: one thread
        for op in _OPS:
            op(x)
