"""Guards of the training loop: finite checks of a step (gradients before the optimiser steps,
parameters after) and SIGINT / SIGTERM turned into a stop request."""
from __future__ import annotations

import contextlib
import logging
import signal
import threading
from collections.abc import Callable, Iterator

import torch

from ..render import fast, uses_fast

log = logging.getLogger("dibrgs.train")


def all_finite(tensors: list[torch.Tensor | None]) -> bool:
    """Whether every element of ``tensors`` (None entries skipped) is finite.

    On the C++ path (when every tensor is float32 / float64 CPU data): one parallel pass over all
    of them in the rasterizer's extension. Otherwise one vectorised sum a tensor: a NaN or an
    infinity makes its sum non-finite, so a finite sum proves the tensor finite; only when a sum
    is not finite (a non-finite element, or finite values overflowing float32) does the exact
    per-element test decide.
    """
    ts = [t for t in tensors if t is not None]
    if not ts:
        return True
    if uses_fast(None, ts[0]):
        found = fast.extension().all_finite(ts)  # -1: a tensor the extension does not test
        if found >= 0:
            return bool(found)
    if bool(torch.isfinite(torch.stack([t.sum() for t in ts])).all()):
        return True
    return all(bool(torch.isfinite(t).all()) for t in ts)


@torch.no_grad()
def make_finite(params: list[torch.Tensor]) -> bool:
    """Replace NaN by 0 and infinities by +-1e6 in place (so absurd learning rates cannot poison
    a run); whether any parameter needed it."""
    if all_finite(params):
        return False
    bad = [p for p in params if not torch.isfinite(p).all()]
    for p in bad:
        torch.nan_to_num_(p, nan=0.0, posinf=1e6, neginf=-1e6)
    return bool(bad)


@contextlib.contextmanager
def stop_on_signals(request_stop: Callable[[], None]) -> Iterator[None]:
    """While inside, SIGINT and SIGTERM call ``request_stop`` (the loop checkpoints and stops
    after the iteration) instead of killing the process; only in the main thread, where Python
    delivers signals."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: object) -> None:
        log.warning("signal %d: checkpointing and stopping after this iteration", signum)
        request_stop()

    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
