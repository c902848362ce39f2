"""What the families' stages share, written once: round 0's resumable recording and the
deployment's per-episode log.

Both are resumable the same way. Round 0 counts the complete episodes the dataset already holds
and records only the rest. A deployment keeps one row per finished episode (its return, and for
the SAM-RL family its success, camera moves and chosen camera) in its round's
``deploy_partial.json``, written atomically after each episode, so a resumed deployment knows
which episodes are done and their figures without reading them back from ``progress.json``
(which only records how many there are).
"""

from __future__ import annotations

import json
import time
from typing import Any, Callable

from twinrl import report
from twinrl.loop.engine import RunContext, episodes_in, real_steps

__all__ = ["collect_round0", "EpisodeLog"]


def collect_round0(run: RunContext, what: str,
                   record: Callable[[range], dict[str, Any] | None]) -> None:
    """Round 0's stage: ``record(range(have, K))`` records the episodes the dataset does not hold
    yet (``have`` complete ones from an interrupted run are kept) and returns extra figures for
    ``progress.json``; ``what`` says what is recorded (``"exciting episodes on the real
    twin"``)."""
    K = run.K
    have = episodes_in(run.dir.dataset)
    run.say(f"[bold]round 0[/]: recording {K - have} {what}"
            f"{f' ({have} already recorded)' if have else ''}")
    t0 = time.perf_counter()
    extra = record(range(have, K)) or {}
    run.prog.mark("round0/collect", real_steps=real_steps(run), **extra,
                  seconds={"collect": time.perf_counter() - t0})


class EpisodeLog:
    """Round ``r``'s deployed episodes so far, one row each, in ``deploy_partial.json`` (a run
    killed by an older twinrl kept them in ``progress.json`` under ``legacy_key``: read there
    when the file does not exist, so such a run resumes)."""

    def __init__(self, run: RunContext, r: int, legacy_key: str):
        self.path = run.dir.round(r).deploy_log
        self._prog, self._r = run.prog, r
        if self.path.exists():
            self.rows = list(json.loads(self.path.read_text())["episodes"])
        else:
            self.rows = list(run.prog.record(r).get(legacy_key, []))

    def __len__(self) -> int:
        return len(self.rows)

    def add(self, row) -> None:
        """One more finished episode's row: written, then counted in ``progress.json``."""
        self.rows.append(report.to_jsonable(row))
        report.write_json(self.path, {"episodes": self.rows})
        self._prog.mark(f"round{self._r}/deploy_partial", deploy_episodes=len(self.rows))
