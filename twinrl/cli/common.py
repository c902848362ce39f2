"""What the commands share: the usage error, the ``--seed``/``--out`` options, the checks of
arguments that several commands take, and MuJoCo's warnings as one line each."""

from __future__ import annotations

import argparse
import time
from pathlib import Path


class UsageError(Exception):
    """Bad input named in one line, no traceback."""


def one_line_warnings(prefix: str) -> None:
    """Print MuJoCo's warnings (``twinrl.physics.MuJoCoWarning``) on the command line as one line
    each, ``PREFIX: warning: ...``, not Python's two (file:line, then the source line that called
    MuJoCo); every other warning keeps Python's format."""
    import warnings

    from twinrl.physics.mjwarn import MuJoCoWarning

    default = warnings.formatwarning

    def formatwarning(message, category, filename, lineno, line=None):
        if issubclass(category, MuJoCoWarning):
            return f"{prefix}: warning: {message}\n"
        return default(message, category, filename, lineno, line)

    warnings.formatwarning = formatwarning


def check_task(name: str, mjcf_hint: str | None = None) -> None:
    """A registered task's name, else one line listing them (with ``mjcf_hint`` when ``name``
    is an MJCF file, which this command does not take)."""
    from twinrl import envs

    if name not in envs.names():
        if mjcf_hint and str(name).lower().endswith(".xml"):
            raise UsageError(f"--env {name}: {mjcf_hint}")
        raise UsageError(f"unknown task {name!r}; registered tasks are {', '.join(envs.names())}")


def is_mjcf(env: str) -> bool:
    """Whether ``--env`` names an MJCF file rather than a registered task."""
    return env.lower().endswith(".xml") or Path(env).is_file()


def at_least_one(args, *flags: str) -> None:
    """One line naming the first of ``flags`` (argparse dests) given and below 1."""
    for flag in flags:
        v = getattr(args, flag)
        if v is not None and v < 1:
            raise UsageError(f"--{flag.replace('_', '-')} must be >= 1, got {v}")


def check_size(size) -> None:
    """``--size W H``: both at least 1 (the renderer's own bound, its offscreen buffer, is
    checked where the model is loaded)."""
    if min(size) < 1:
        raise UsageError(f"--size {size[0]} {size[1]}: width and height must be >= 1")


def add_common(p: argparse.ArgumentParser, out_default: str) -> None:
    """The options every command takes: ``--seed`` and ``--out DIR`` (default ``out_default``)."""
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", type=Path, default=Path(out_default),
                   help=f"output directory (default {out_default})")


QUIET_FOR = 2.0
"""Seconds a command's stage runs before ``ProgressLines`` prints it."""


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
