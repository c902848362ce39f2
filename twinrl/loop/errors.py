"""``LoopError``: what every part of the loop raises for bad settings or a mismatched resume."""

__all__ = ["LoopError"]


class LoopError(Exception):
    """Bad loop settings or a mismatched resume."""
