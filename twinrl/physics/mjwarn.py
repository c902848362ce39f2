"""MuJoCo's C warnings as Python warnings, with no ``MUJOCO_LOG.TXT`` left in the working directory.

MuJoCo's C library reports a warning (``mju_warning``: a deprecated MJCF attribute such as
Gymnasium's ``half_cheetah.xml``'s ``settotalmass``, an unstable simulation's "Nan, Inf or huge
value in QACC") by printing it and appending it, time-stamped, to ``MUJOCO_LOG.TXT`` in the
process's working directory -- a file a user finds beside their own after ``twinrl gradcheck
their.xml``, from any directory they ran it in. Unless a handler is installed: MuJoCo then calls the
handler instead (``mujoco.set_mju_user_warning``) and neither prints nor writes. ``MjSpec.compile``
raises the same messages as plain Python ``UserWarning``s instead.

``mujoco_warnings(where)`` installs such a handler around a block -- compiling an MJCF, stepping a
real twin -- and re-raises what MuJoCo said there as ``MuJoCoWarning``s (a ``UserWarning``) naming
``where``, each distinct message once (a plain ``UserWarning`` raised in the block counts as
MuJoCo's: the blocks call nothing else; other categories pass through unchanged). Python's warning
filters then decide: shown once per place by default, ``warnings.simplefilter("error",
MuJoCoWarning)`` turns them into errors, ``warnings.catch_warnings(record=True)`` records them. The
handler that was installed before (yours, if any; MuJoCo's default if none) is restored on exit;
twinrl changes no MuJoCo setting outside these blocks.
"""

from __future__ import annotations

import contextlib
import warnings

import mujoco

__all__ = ["MuJoCoWarning", "mujoco_warnings"]


class MuJoCoWarning(UserWarning):
    """A warning of MuJoCo's C library (``mju_warning``), raised where twinrl called MuJoCo."""


@contextlib.contextmanager
def mujoco_warnings(where: str, stacklevel: int = 3):
    """Run a block with MuJoCo's warnings collected, then warn each distinct one as a
    ``MuJoCoWarning`` ``"{where}: MuJoCo: {message}"`` (module docstring). ``stacklevel`` is
    ``warnings.warn``'s, counted from the caller of the ``with`` block's function by default."""
    said: list[str] = []
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(said.append)
    try:
        with warnings.catch_warnings(record=True) as python:
            warnings.simplefilter("always")
            yield said
    finally:
        mujoco.set_mju_user_warning(previous)
        for w in python:  # MjSpec.compile raises MuJoCo's warnings as plain UserWarnings
            if w.category is UserWarning:
                said.append(str(w.message))
            else:  # anything else passes through as it was raised
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        for message in dict.fromkeys(" ".join(str(m).split()) for m in said):
            warnings.warn(f"{where}: MuJoCo: {message}", MuJoCoWarning, stacklevel=stacklevel)
