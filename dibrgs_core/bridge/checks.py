"""The add-on's "Set up / Check": what ``dibrgs check --json`` reports, folded for display.

The check runs in the training interpreter (``bridge.jobs.check_command``), in the
background; every stdout line goes through :meth:`CheckReport.feed`. Lines are
described in :mod:`dibrgs_core.commands.check`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from .progress import parse_progress_line


@dataclass
class CheckItem:
    name: str
    ok: bool
    required: bool = True
    detail: str = ""
    fix: str | None = None
    note: str | None = None


@dataclass
class CheckReport:
    """Items so far, the step running now, and the result once the check has ended."""

    items: list[CheckItem] = field(default_factory=list)
    index: int = 0
    total: int = 0
    stage: str | None = None
    #: ``{"ok", "missing", "fix"}`` from the last line; None while running or when the check died.
    result: dict | None = None

    def feed(self, line: str) -> bool:
        """Fold one output line in; False for lines that are not check events."""
        ev = parse_progress_line(line)
        if ev is None:
            return False
        if isinstance(ev.get("check"), str):
            self.items.append(CheckItem(name=ev["check"], ok=bool(ev.get("ok")),
                                        required=bool(ev.get("required", True)), detail=str(ev.get("detail") or ""),
                                        fix=ev.get("fix") or None, note=ev.get("note") or None))
            self.index = int(ev.get("index") or len(self.items))
            self.total = max(int(ev.get("total") or 0), self.index)
            self.stage = None
            return True
        if isinstance(ev.get("stage"), str):
            self.stage = ev["stage"]
            return True
        if isinstance(ev.get("result"), dict):
            self.result = ev["result"]
            self.stage = None
            return True
        return False

    @property
    def fraction(self) -> float:
        return 1.0 if self.result is not None else (self.index / self.total if self.total else 0.0)

    @property
    def ok(self) -> bool | None:
        """True/False once the check has reported its result, None before."""
        return None if self.result is None else bool(self.result.get("ok"))

    def text(self) -> str:
        """One line for the progress bar."""
        if self.result is not None:
            return "ready to train" if self.ok else "not ready: " + ", ".join(self.problems())
        if self.stage:
            return self.stage
        last = self.items[-1].name if self.items else "starting"
        return f"checked {last} ({self.index}/{self.total or '?'})"

    def problems(self) -> list[str]:
        """Names of the required items that failed."""
        return [i.name for i in self.items if i.required and not i.ok]
