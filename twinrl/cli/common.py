"""What the commands share: the usage error, the ``--seed``/``--out`` options, the checks of
arguments that several commands take, and MuJoCo's warnings as one line each."""

from __future__ import annotations

import argparse
from pathlib import Path

from twinrl.progress import QUIET_FOR, ProgressLines  # noqa: F401  (re-exported)


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


# ``ProgressLines`` lives in ``twinrl.progress`` (the trainers use it too); kept importable here.
