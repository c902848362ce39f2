"""Progress as dim lines, for logs as well as terminals: what a command or a training prints
while it works when no live progress bar can show (a log file, a pipe, a non-interactive
console), held back for the first seconds so quick work stays quiet."""

from __future__ import annotations

import os
import time

__all__ = ["QUIET_FOR", "ProgressLines"]


def _progress_after(default: float = 2.0) -> float:
    text = os.environ.get("TWINRL_PROGRESS_AFTER", "")
    try:
        value = float(text)
    except ValueError:
        return default  # unset, or not a number: the default (progress is no reason to fail)
    return value if value >= 0 else default


QUIET_FOR = _progress_after()
"""Seconds a command's stage runs before ``ProgressLines`` prints it (the environment's
``TWINRL_PROGRESS_AFTER``, 2 unless set to a number >= 0; 0 prints every stage, however
quick)."""


class ProgressLines:
    """Progress as dim lines with the time since the work began, for logs as well as terminals
    (a status spinner prints nothing into a log). Held back for the first ``QUIET_FOR`` seconds
    -- then the stage under way is printed, from a timer if the work is still silent in it -- so
    quick work finishes without them; ``tick`` prints at most one line every ``every`` seconds
    (a loop's iterations). ``close()`` when the work ends."""

    def __init__(self, name: str, every: float = 20.0):
        import threading

        self.name, self.every, self.t0, self.pending = name, every, time.perf_counter(), []
        self.last = -every
        self.lock, self.open = threading.Lock(), False
        self.timer = threading.Timer(QUIET_FOR, self._release)
        self.timer.daemon = True
        self.timer.start()

    def _print(self, msg: str) -> None:
        from twinrl import report

        report.console.print(f"[dim]{self.name} [{time.perf_counter() - self.t0:4.0f} s] "
                             f"{msg}[/dim]")

    def _release(self) -> None:
        with self.lock:
            self.open = True
            for m in self.pending:
                self._print(m)
            self.pending.clear()

    def __call__(self, msg: str) -> None:
        with self.lock:
            if self.open:
                self._print(msg)
            else:
                self.pending.append(msg)

    def tick(self, msg: str) -> None:
        """``msg``, unless a tick printed less than ``every`` seconds ago (a loop's
        iterations: one line now and then, not one per iteration)."""
        now = time.perf_counter() - self.t0
        if now - self.last >= self.every:
            self.last = now
            self(msg)

    def close(self) -> None:
        self.timer.cancel()
