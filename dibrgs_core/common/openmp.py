"""How OpenMP's worker threads wait between parallel regions: chosen once, before torch is imported.

A training iteration is hundreds of small parallel regions (torch operators on tens of thousands
of Gaussians). Measured on 2 cores (docs/benchmarks.md, "Training iteration"), a DIBR-GS iteration
at 256x256 with two threads:

* workers that go to sleep at once (``OMP_WAIT_POLICY=PASSIVE``) pay a wake-up in every region:
  two threads take longer than one;
* workers that spin a while before sleeping catch the next region. A spin is counted in
  ``pause`` instructions, whose length differs several-fold between CPUs (5 ns on the Cascade Lake
  host, 12 ns on the Ice Lake one), and it must outlast the Python between two extension calls
  (up to about a millisecond): at 10,000 spins (0.12 ms on the Ice Lake) the worker still slept
  in many gaps, and waking it cost 0.9-2.9 ms a step of waiting at region starts; at 100,000
  (0.5-1.2 ms) 0.1 ms, and the benchmark's two-thread step took 0.65-0.66x the one-thread time
  instead of 0.72x (medians; docs/benchmarks.md, session 39);
* but spinning workers take the cores from any other busy process: two two-thread runs side by
  side each ran over twice as long as with passive waiting.

So the short spin is used when the CPUs are idle as the command starts, passive waiting when they
are not. libgomp (torch's OpenMP on Linux) reads these variables once, when it loads; a user's own
``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` is left alone. Standard library only.
"""
from __future__ import annotations

import os
import time
from typing import MutableMapping

#: Spin iterations before a waiting worker sleeps when the machine is idle (see above).
SHORT_SPIN = "100000"
#: The CPUs count as idle when fewer than this many of them were busy (summed over all CPUs).
IDLE_BUSY_CPUS = 0.5

_choice = "not chosen (set_wait_policy was not called before torch)"


def busy_cpus(window_s: float = 0.1) -> float | None:
    """How many CPUs were busy, summed, over ``window_s`` seconds (from /proc/stat; None elsewhere)."""

    def sample() -> tuple[list[int], int]:
        with open("/proc/stat") as f:
            lines = f.read().splitlines()
        total = [int(x) for x in lines[0].split()[1:]]
        n = sum(1 for ln in lines[1:] if ln.startswith("cpu"))
        return total, n

    try:
        a, n = sample()
        time.sleep(window_s)
        b, _ = sample()
    except (OSError, ValueError, IndexError):
        return None
    d = [y - x for x, y in zip(a, b)]
    total = sum(d[:8])  # user nice system idle iowait irq softirq steal (guest time is inside user)
    idle = d[3] + d[4]
    return n * (1.0 - idle / total) if total > 0 else None


def set_wait_policy(environ: MutableMapping[str, str] = os.environ, busy: float | None = None) -> str:
    """Set the wait policy in ``environ`` unless the user set one; returns what was decided and why.
    ``busy``: CPUs busy now (default: measured by :func:`busy_cpus`)."""
    global _choice
    if "OMP_WAIT_POLICY" in environ or "GOMP_SPINCOUNT" in environ:
        _choice = "the user's OMP_WAIT_POLICY / GOMP_SPINCOUNT"
        return _choice
    busy = busy_cpus() if busy is None else busy
    if busy is not None and busy < IDLE_BUSY_CPUS:
        environ["GOMP_SPINCOUNT"] = SHORT_SPIN
        _choice = f"short spin (GOMP_SPINCOUNT={SHORT_SPIN}): the CPUs were idle at start ({busy:.2f} busy)"
    else:
        environ["OMP_WAIT_POLICY"] = "PASSIVE"
        why = "CPU use unknown" if busy is None else f"{busy:.2f} CPUs busy at start"
        _choice = f"passive (OMP_WAIT_POLICY=PASSIVE): {why}"
    return _choice


def wait_policy() -> str:
    """What :func:`set_wait_policy` decided in this process, for the log and the report."""
    return _choice
