"""The oracle (evaluation only) trained in a child process beside the cartpole family's stages.

The oracle is a policy trained the same way as the loop's in a simulator given the twin's *true*
parameters, evaluated on the real twin (``twinrl.eval.oracle_return``); it is never fed back.
"""

from __future__ import annotations

from pathlib import Path

from twinrl import eval as evaluation
from twinrl.loop.errors import LoopError

__all__ = ["OracleProcess"]


def _oracle_child(conn, env_name, seed, out, config, perturbation, nice, parent, secret=None):
    """The oracle's process: lower priority, dies with its parent, sends back the return or the
    error's text."""
    import os
    import signal
    import traceback

    try:  # Linux: SIGKILL when the parent dies, so a killed loop leaves no orphan training
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    # A spawned child gets here after seconds of imports; a parent killed before the prctl sent
    # no signal, so check it is still the parent.
    if os.getppid() != parent:
        os._exit(1)
    os.nice(nice)
    try:
        conn.send(("ok", evaluation.oracle_return(env_name, seed, out, config, False,
                                                  perturbation, secret)))
    except BaseException:  # noqa: BLE001  (sent to the parent, which raises it)
        conn.send(("error", traceback.format_exc()))
    conn.close()


class OracleProcess:
    """The oracle trained in a child process at a lower CPU priority (``nice``) while the loop's
    stages run: it needs nothing the loop records, and the scheduler gives it the CPU the stages
    leave idle (on 2 cores: sysid's and the residual's single-threaded compiles) instead of
    halving the stages' share, as a thread in this process did. The child dies with this process
    (a killed loop leaves no orphan); the oracle resumes from its own checkpoints."""

    def __init__(self, env_name, seed, out, config, perturbation, nice: int = 10, secret=None):
        import multiprocessing as mp
        import os

        ctx = mp.get_context("spawn")  # a fresh interpreter: JAX is not fork-safe
        self._conn, child = ctx.Pipe(duplex=False)
        self._proc = ctx.Process(target=_oracle_child, name="twinrl-oracle", daemon=True,
                                 args=(child, env_name, seed, Path(out), config, perturbation,
                                       nice, os.getpid(), secret))
        self._proc.start()
        child.close()

    def running(self) -> bool:
        return self._proc.is_alive() and not self._conn.poll()

    def result(self) -> float:
        try:
            status, value = self._conn.recv()
        except EOFError:
            self._proc.join()
            raise LoopError(f"the oracle's process died (exit code {self._proc.exitcode}) "
                            f"before reporting") from None
        self._proc.join()
        if status == "error":
            raise LoopError(f"the oracle's training failed:\n{value}")
        return value

