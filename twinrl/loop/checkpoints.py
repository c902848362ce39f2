"""What a directory twinrl wrote holds, and which command takes it.

Every directory a command writes says what it is: a policy checkpoint in its
``checkpoint.json``'s ``kind`` (``twinrl.learn.checkpoint.KINDS``: a state policy, an image
actor, a sensing-aware Q, a residual policy, a residual dynamics model), a ``twinrl train`` run
in its ``run.json``, a ``twinrl run`` in its ``loop.json`` and each of its rounds in
``round<r>/round.json``, ``twinrl sense`` and ``twinrl eval`` in their ``summary.json``, a
recorded dataset in its ``meta.json``. Directories written before those records existed are told
apart by their layout. ``describe(path)`` reads that; ``require(path, command, kinds)`` gives
what ``command`` takes, or one line saying what ``path`` is and the command that takes it.
"""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path
from typing import Any

from twinrl.learn.checkpoint import KINDS, CheckpointError, read_meta
from twinrl.loop.rundir import RoundDir, RunDir

__all__ = ["DIRECTORY_KINDS", "RECORDED_IN", "TAKES", "Found", "describe", "require",
           "latest_round", "arm_run", "round_of", "round_q", "sensing_q"]

DIRECTORY_KINDS = {
    "run": "a `twinrl run` output directory",
    "round": "a round of a `twinrl run` (round<r>/)",
    "sense": "a `twinrl sense` output (the chosen camera pose; it holds no checkpoint)",
    "eval": "a `twinrl eval` output (returns and success; it holds no checkpoint)",
    "dataset": "a recorded dataset of real transitions",
}
"""The kinds of directory that are not a policy checkpoint themselves."""

RECORDED_IN = {"policy": "checkpoint.json", "image_actor": "checkpoint.json",
               "sensing_q": "checkpoint.json", "residual": "checkpoint.json",
               "hybrid_residual": "checkpoint.json", "run": "loop.json", "round": "round.json",
               "sense": "summary.json", "eval": "summary.json", "dataset": "meta.json"}
"""The file whose ``kind`` (or, for a dataset, whose presence) says what a directory is."""

TAKES = {"eval": ("policy", "image_actor", "run", "round"),
         "sense": ("sensing_q", "run", "round"),
         "train --algo sensing --set actor=": ("image_actor",),
         "sysid --from": ("dataset", "run")}
"""The kinds each command that reads checkpoints takes (a ``twinrl train`` run directory counts
as the kind of its ``policy/``); every other kind is refused in one line (``require``)."""


@dataclasses.dataclass(frozen=True)
class Found:
    """What ``describe`` found at ``path``."""

    kind: str
    """One of ``twinrl.learn.checkpoint.KINDS`` or ``DIRECTORY_KINDS``."""
    path: Path
    """The directory (a policy's, for a ``twinrl train`` run given by its directory: its
    ``policy/``)."""
    meta: dict[str, Any]
    """Its record: ``checkpoint.json``, ``loop.json``, ``round.json``, ``meta.json`` or
    ``summary.json``."""
    run: RunDir | None = None
    """The ``twinrl run`` it belongs to (a round, or a checkpoint inside a round), if any."""
    round: RoundDir | None = None
    """The round it belongs to (or is), if any."""
    given: Path | None = None
    """The path as given (a training run's directory, where ``path`` is its policy)."""

    @property
    def env(self) -> str | None:
        """The task it was made for, where its record names one."""
        env = self.meta.get("env")
        return env if isinstance(env, str) else None

    def describe(self) -> str:
        """One phrase: what it is."""
        return {**KINDS, **DIRECTORY_KINDS}[self.kind]


def _json(path: Path) -> dict[str, Any] | None:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def _run_of(path: Path) -> RunDir | None:
    """The ``twinrl run`` directory ``path`` is (``loop.json`` and ``progress.json``), if so."""
    return RunDir(path) if (path / "loop.json").is_file() and (
        path / "progress.json").is_file() else None


def _round_of(path: Path) -> tuple[RunDir, RoundDir] | None:
    """``(run, round)`` when ``path`` is ``round<r>/`` of a ``twinrl run``."""
    if re.fullmatch(r"round\d+", path.name) and (run := _run_of(path.parent)) is not None:
        return run, RoundDir(path)
    return None


def describe(path: str | Path) -> Found:
    """What the directory ``path`` holds (module docstring); a ``CheckpointError`` naming the
    path when it is none of twinrl's."""
    path = Path(path).absolute()
    if not path.exists():
        raise CheckpointError(f"{path} does not exist")
    if not path.is_dir():
        raise CheckpointError(f"{path} is a file; twinrl's checkpoints are directories")
    if (path / "checkpoint.json").is_file() or (path / "policy" / "checkpoint.json").is_file():
        policy, meta = read_meta(path)  # a training run's directory: its policy/
        home = policy.parent if policy.name == "policy" else policy  # a training run's
        where = _round_of(home.parent)
        return Found(meta["kind"], policy, meta, *(where or (None, None)), given=path)
    if (run := _run_of(path)) is not None:
        return Found("run", path, _json(run.settings) or {}, run, given=path)
    if (where := _round_of(path)) is not None:
        settings = _json(where[0].settings) or {}
        return Found("round", path, {**(_json(path / "round.json") or {}),
                                     "env": settings.get("env"), "seed": settings.get("seed")},
                     *where, given=path)
    if (path / "meta.json").is_file() and any(path.glob("chunk-*")):
        return Found("dataset", path, _json(path / "meta.json") or {}, given=path)
    summary = _json(path / "summary.json") or {}
    if summary.get("kind") in ("sense", "eval") or "chosen_pose" in summary:
        return Found(summary.get("kind", "sense"), path, summary, given=path)
    if "returns" in summary and "where" in summary:
        return Found("eval", path, summary, given=path)
    raise CheckpointError(f"{path}: not a directory twinrl wrote (no checkpoint.json, run.json, "
                          f"loop.json or summary.json)")


def latest_round(run: RunDir) -> RoundDir | None:
    """The last round of ``run`` with a deployed policy (an actor or a trained policy)."""
    rounds = sorted((int(p.name[5:]), p) for p in run.out.glob("round*")
                    if re.fullmatch(r"round\d+", p.name))
    for _, p in reversed(rounds):
        rd = RoundDir(p)
        if (rd.actor / "policy" / "checkpoint.json").is_file() or (
                rd.train / "policy" / "checkpoint.json").is_file():
            return rd
    return None


def arm_run(found: Found) -> bool:
    """Whether ``found`` belongs to a SAM-RL (manipulation) run, by its task."""
    from twinrl.loop.arm_config import is_arm_task

    env = found.env
    if env is None and found.run is not None:
        env = (_json(found.run.settings) or {}).get("env")
    return bool(env) and is_arm_task(env)


def _hint(found: Found, command: str) -> str:
    """The command that takes ``found``, for the refusal of ``command``."""
    p, k = found.given or found.path, found.kind
    if k == "sensing_q":
        return f"`twinrl sense --env {found.env} --checkpoint {p}` chooses a camera pose with it"
    if k in ("policy", "image_actor"):
        return f"`twinrl eval --checkpoint {p}` runs it"
    if k == "residual":
        where = found.round.path if found.round is not None else "ROUND"
        return (f"it corrects its round's actor or policy: `twinrl eval --checkpoint {where}` "
                f"evaluates the round with it")
    if k == "hybrid_residual":
        return "it is not a policy: `twinrl run` trains the residual policy through it"
    if k in ("run", "round"):
        if command == "sense" and not arm_run(found):
            return "a run of the cartpole family has no sensing-aware Q"
        return f"`twinrl eval --checkpoint {p}` evaluates its deployed policy"
    if k == "dataset":
        return f"`twinrl sysid --env {found.env} --from {p}` identifies a twin from it"
    return "it holds no checkpoint"


def require(path: str | Path, command: str, kinds: tuple[str, ...]) -> Found:
    """``describe(path)`` when it is one of ``kinds``; else a ``CheckpointError`` in one line:
    what it is, and the command that takes it."""
    found = describe(path)
    if found.kind in kinds:
        return found
    raise CheckpointError(f"{found.given or found.path} is {found.describe()}, which "
                          f"`twinrl {command}` does not take; {_hint(found, command)}")


def round_of(found: Found) -> RoundDir | None:
    """The round ``found`` is, or belongs to (a run: its last with a deployed policy)."""
    return latest_round(found.run) if found.kind == "run" else found.round


def sensing_q(path: str | Path, command: str = "sense") -> Path:
    """The sensing-aware Q ``path`` names: itself (or a ``twinrl train --algo sensing`` run's
    policy), or the ``q/`` of a manipulation run's round (a run: its last round); any other
    directory refused in one line naming the command that takes it."""
    found = require(path, command, TAKES["sense"])
    if found.kind == "sensing_q":
        return found.path
    if not arm_run(found):
        require(found.path, command, ())  # refused: a cartpole-family run has no Q
    q = round_q(found)
    if q is None:
        raise CheckpointError(f"{found.path}: no sensing-aware Q trained there yet "
                              f"(round<r>/q/)")
    return q


def round_q(found: Found) -> Path | None:
    """The trained sensing-aware Q of the round ``found`` is or belongs to (a run: its last
    round), or None."""
    rdir = round_of(found)
    return rdir.q if rdir is not None and (rdir.q / "policy" / "checkpoint.json").is_file() \
        else None
