"""A call run in a background thread (``gradcheck``'s XLA compiles, which release Python's lock,
overlapping its tracing)."""

from __future__ import annotations

import threading
import time

__all__ = ["Background"]


class Background:
    """``fn(*args, **kwargs)`` run in a daemon thread (an XLA compile, which releases Python's
    lock): ``result()`` waits for it and returns its value or raises its error; ``seconds`` is
    how long it ran. Daemon: an interrupted check does not wait for a compile to finish."""

    def __init__(self, fn, *args, **kwargs):
        self.seconds, self._value, self._error = 0.0, None, None

        def run():
            t0 = time.perf_counter()
            try:
                self._value = fn(*args, **kwargs)
            except BaseException as e:  # handed to the caller of result()
                self._error = e
            self.seconds = time.perf_counter() - t0

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def result(self):
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._value
