"""Progress of a ``dibrgs train --progress-json`` run, as the add-on shows it.

The training prints one JSON object per line on stdout:
``{"stage": "compiling the rasterizer (first run, about 2 minutes)"}`` or
``{"stage": "building 96 pseudo views", "done": 3, "total": 96}`` before and
during a long set-up step, ``{"iteration", "total", "loss", "eta_s",
"elapsed_s"}`` while it trains and ``{"done": true, "work": ...}`` at the
end. Any other line (a log line that slipped onto stdout) is not progress and
is ignored here.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any


def parse_progress_line(line: str) -> dict[str, Any] | None:
    """The JSON object on a progress line, or None for any other line."""
    s = line.strip()
    if not (s.startswith("{") and s.endswith("}")):
        return None
    try:
        obj = json.loads(s)
    except ValueError:
        return None
    return obj if isinstance(obj, dict) else None


def _finite(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def format_duration(seconds: float | None) -> str:
    """``h:mm:ss`` or ``m:ss``; ``--:--`` when unknown (None, NaN, negative)."""
    s = _finite(seconds)
    if s is None or s < 0:
        return "--:--"
    s = int(round(s))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


@dataclass
class Progress:
    """Latest known state of a training run (all times in seconds)."""

    iteration: int = 0
    total: int = 0
    loss: float | None = None
    eta_s: float | None = None
    elapsed_s: float | None = None
    done: bool = False
    work: str | None = None
    #: The set-up step running now (None once iterations are reported), and its
    #: count of finished items when it has one.
    stage: str | None = None
    stage_done: int | None = None
    stage_total: int | None = None

    def update(self, event: dict[str, Any]) -> None:
        """Fold one progress event in; unknown or malformed fields are ignored."""
        if isinstance(event.get("stage"), str):  # its "done" is a count, not the end of the run
            done, total = _finite(event.get("done")), _finite(event.get("total"))
            self.stage = event["stage"]
            self.stage_total = int(total) if total is not None and total > 0 else None
            self.stage_done = (min(max(int(done), 0), self.stage_total)
                               if done is not None and self.stage_total else None)
            return
        if event.get("done") is True:
            self.done = True
            self.work = str(event["work"]) if event.get("work") is not None else self.work
            if self.total:
                self.iteration = self.total
            self.eta_s = 0.0
            return
        it, tot = _finite(event.get("iteration")), _finite(event.get("total"))
        if it is not None:
            self.iteration = max(0, int(it))
            self.stage = self.stage_done = self.stage_total = None
        if tot is not None and tot > 0:
            self.total = int(tot)
        for key in ("loss", "eta_s", "elapsed_s"):
            if key in event:
                setattr(self, key, _finite(event[key]))

    @property
    def fraction(self) -> float:
        """Completed fraction in [0, 1] (1 once done); of the set-up step while one runs."""
        if self.done:
            return 1.0
        if self.stage is not None:
            return self.stage_done / self.stage_total if self.stage_done is not None else 0.0
        if self.total <= 0:
            return 0.0
        return min(max(self.iteration / self.total, 0.0), 1.0)

    def text(self) -> str:
        """One line for the panel, e.g. ``it 120/300  loss 0.0412  ETA 0:42`` or
        ``building 96 pseudo views 3/96``."""
        if self.done:
            return "done"
        if self.stage is not None:
            return self.stage + (f" {self.stage_done}/{self.stage_total}" if self.stage_done is not None else "")
        if self.total == 0 and self.iteration == 0:
            return "starting"
        parts = [f"it {self.iteration}/{self.total or '?'}"]
        if self.loss is not None:
            parts.append(f"loss {self.loss:.4g}")
        parts.append(f"ETA {format_duration(self.eta_s)}")
        return "  ".join(parts)
