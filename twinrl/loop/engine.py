"""The loop's engine, written once for every task family: ``Stage``, the round driver with its
progress and resume, the settings check, and the skeleton of a run's start and finish.

A task family (``Family``: the cartpole family's ``twinrl.loop.cartpole``, SAM-RL's
``twinrl.loop.arm``) supplies its config class, its round-0 stage and the stages of every later
round, how its real twin is opened, which records make a round's row, and its outputs. ``run``
then walks the rounds: round 0's stage, then for each round ``r >= 1`` every stage in order, each
given the values earlier stages gave (``Stage.needs`` / ``Stage.gives``) and the round's ``data``
(every intact real transition so far).

Several processes (``jax.distributed``, ``twinrl run --coordinator ...``): process 0 runs the
loop as one process does (the real twin, every file); every other process follows it
(``follow``): it waits for each stage process 0 marks done in ``progress.json`` (a file system
they share) and reads the stage's values back from its files, and runs the ``shared`` stages --
the learners, data-parallel over every process's devices -- together with process 0. It opens
no real twin and writes nothing.

Resume: every stage writes its outputs, then marks itself done in ``progress.json`` (atomically);
a stage marked done is not run again, its values are read back from its own files
(``Stage.load``). ``progress.json`` is a record: no stage takes a decision from it. Real episodes
go to ``dataset/`` as they happen, so a run killed at any moment loses nothing recorded.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from twinrl import report
from twinrl.loop.errors import LoopError
from twinrl.loop.rundir import RunDir

__all__ = ["LoopError", "Progress", "RunContext", "Stage", "Family", "run", "follow",
           "check_settings", "read_dataset", "episodes_in", "real_steps", "quiet",
           "seconds_so_far", "POLL_S"]

POLL_S = 0.5
"""Seconds between a following process's reads of ``progress.json`` (``follow``)."""


class Progress:
    """``progress.json``: the finished stages and the per-round records, written atomically."""

    def __init__(self, path: Path):
        self.path = path
        self.doc = json.loads(path.read_text()) if path.exists() else {"done": [], "rounds": {}}

    def done(self, stage: str) -> bool:
        return stage in self.doc["done"]

    def mark(self, stage: str, **record: Any) -> None:
        if record:
            r = stage.split("/")[0]
            self.doc["rounds"].setdefault(r, {}).update(report.to_jsonable(record))
        if stage not in self.doc["done"]:
            self.doc["done"].append(stage)
        report.write_json(self.path, self.doc)

    def record(self, r: int) -> dict[str, Any]:
        return self.doc["rounds"].get(f"round{r}", {})


class _Followed(Progress):
    """Process 0's ``progress.json`` as a following process sees it: read again at every
    ``done``; ``mark`` keeps the record in memory (process 0 alone writes the file)."""

    def done(self, stage: str) -> bool:
        if self.path.exists():
            try:
                self.doc = json.loads(self.path.read_text())
            except json.JSONDecodeError:  # written atomically; a torn read is retried later
                return False
        return stage in self.doc["done"]

    def mark(self, stage: str, **record: Any) -> None:
        if record:
            self.doc["rounds"].setdefault(stage.split("/")[0], {}).update(
                report.to_jsonable(record))


@dataclasses.dataclass
class RunContext:
    """What every stage sees: the run's settings, its directory, the real twin (a
    ``TwinClient``), the dataset writer and the two records (``progress.json`` for the stages,
    ``eval/evaluation.json`` for evaluation, which no stage reads)."""

    env_name: str
    seed: int
    dir: RunDir
    config: Any
    perturbation: Any
    twin: Any
    writer: Any
    prog: Progress
    ev: Progress
    say: Callable[..., None]
    progress: bool
    nominal_env: Any
    t_start: float
    background: Any = None
    """A family's evaluation job running beside the stages (the cartpole family's oracle)."""

    @property
    def out(self) -> Path:
        return self.dir.out

    @property
    def secret(self) -> Path:
        return self.dir.secret

    @property
    def K(self) -> int:
        return self.config.episodes_per_round

    def close(self) -> None:
        self.writer.close()
        self.twin.close()


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage of a round. ``make(run, r, rdir, **needs)`` computes the stage's values, saves them
    under ``rdir`` (a ``RoundDir``), marks ``round<r>/<name>`` done in ``progress.json`` and returns
    them: the dict of the values named in ``gives``, which later stages take by name (``needs``); a
    ``make`` that returns None gives what ``load`` reads back. A stage marked done is not run again
    on ``--resume``: ``load(run, rdir, **needs)`` reads its values back from the files it saved. A
    stage whose ``enabled(config)`` is false gives None for each of its values."""

    name: str
    needs: tuple[str, ...]
    gives: tuple[str, ...]
    make: Callable[..., dict[str, Any] | None]
    load: Callable[..., dict[str, Any]] = lambda run, rdir, **_: {}
    enabled: Callable[[Any], bool] = lambda config: True
    shared: bool = False
    """Under several processes, run by every process together (a learner that splits its batch
    over every process's devices and writes from process 0 alone); a stage that is not runs on
    process 0 alone, and the others read its values back (``follow``)."""

    def __call__(self, run: RunContext, r: int, values: dict[str, Any]) -> dict[str, Any]:
        if not self.enabled(run.config):
            return dict.fromkeys(self.gives)
        rdir = run.dir.round(r)
        if r:  # round 0 records into the dataset only
            rdir.make()
        needs = {k: values[k] for k in self.needs}
        if run.prog.done(f"round{r}/{self.name}"):
            given = self.load(run, rdir, **needs)
        else:
            given = self.make(run, r, rdir, **needs)
            if given is None:  # a stage that returns nothing gives what it saved
                given = self.load(run, rdir, **needs)
        if set(given) != set(self.gives):  # the declaration is what later stages rely on
            raise LoopError(f"stage {self.name!r} gave {sorted(given)}, but declares "
                            f"{sorted(self.gives)}")
        return given


@dataclasses.dataclass(frozen=True)
class Family:
    """What a task family supplies to the engine. ``check_task(env_name, config)`` refuses a task
    the family cannot run (before any work); ``open(run_dir, env_name, config, seed, perturbation,
    say)`` returns ``(nominal_env, twin, writer, background)``: the task as the family simulates it,
    the real twin's client, the dataset writer and an evaluation job run beside the stages (or
    None); ``record_keys`` are the ``progress.json`` records that make a round's row of the summary
    (each with its default); ``summarise(run, summary)`` adds the family's figures to the summary
    once the stages are done (evaluation merged in); ``final_video(run, values)`` writes
    ``final.mp4`` from the last round's values; ``write_outputs(run, summary)`` writes
    ``summary.json`` and the family's table and plots."""

    name: str
    config_class: type
    collect: Stage
    round: tuple[Stage, ...]
    check_task: Callable[[str, Any], None]
    open: Callable[..., tuple[Any, Any, Any, Any]]
    record_keys: Mapping[str, Any]
    summarise: Callable[[RunContext, dict], None]
    final_video: Callable[[RunContext, dict], Path]
    write_outputs: Callable[[RunContext, dict], None]


def run(family: Family, env_name: str, out: str | Path, config, *, seed: int = 0,
        resume: bool = False, progress: bool = True, perturbation=None) -> dict[str, Any]:
    """Run ``family``'s loop on ``env_name``'s real twin (hidden perturbation drawn from ``seed``,
    or ``perturbation``) into ``out``; returns the summary (also ``out/summary.json``)."""
    if not isinstance(config, family.config_class):
        raise LoopError(f"the {family.name} loop takes a {family.config_class.__name__}, got "
                        f"{type(config).__name__}")
    from twinrl.learn import distributed

    if distributed.is_distributed():
        if not any(stage.shared for stage in family.round):
            raise LoopError(f"the {family.name} loop runs on one process (none of its stages is "
                            f"distributed); start it without --coordinator")
        if not distributed.is_writer():
            return follow(family, env_name, out, config, seed=seed)
    rd = RunDir(check_settings(family, env_name, Path(out), config, seed, resume))
    ctx = _start(family, rd, env_name, config, seed, progress, perturbation)
    rounds: list[dict[str, Any]] = []
    values: dict[str, Any] = {}
    try:
        family.collect(ctx, 0, {})
        rounds.append(_round_record(family, ctx.prog, 0))
        for r in range(1, config.rounds + 1):
            ctx.say(f"[bold]round {r}[/] ({time.perf_counter() - ctx.t_start:.0f} s)")
            values = {"data": read_dataset(rd.dataset, ctx.say)}
            for stage in family.round:
                values.update(stage(ctx, r, values))
            rounds.append(_round_record(family, ctx.prog, r))
    finally:
        ctx.close()
    return _finish(family, ctx, rounds, values)


def follow(family: Family, env_name: str, out: str | Path, config, *, seed: int = 0,
           poll_s: float = POLL_S) -> dict[str, Any]:
    """A process other than process 0 in a loop on several processes (module docstring): wait
    for each stage process 0 runs alone and read its values back, run the ``shared`` stages with
    it, then wait for process 0's ``summary.json``; returns ``{}`` (process 0 has the summary).
    Process 0 checks the settings and writes every file; a process that stops (an error, a
    kill) ends the others through the runtime (``twinrl.learn.distributed``)."""
    rd = RunDir(Path(out))

    def written():  # summary.json as it stands (rewritten by a rename: a new inode)
        st = rd.summary.stat() if rd.summary.exists() else None
        return st and (st.st_ino, st.st_mtime_ns, st.st_size)

    before = written()
    ctx = RunContext(env_name, int(seed), rd, config, None, None, None, _Followed(rd.progress),
                     _Followed(rd.evaluation), quiet, False, None, time.perf_counter())

    def wait(stage: str) -> None:
        while not ctx.prog.done(stage):
            time.sleep(poll_s)

    last = "round0/collect"
    wait(last)
    for r in range(1, config.rounds + 1):
        values: dict[str, Any] = {"data": read_dataset(rd.dataset)}
        for stage in family.round:
            if stage.enabled(config) and not stage.shared:
                wait(f"round{r}/{stage.name}")
            values.update(stage(ctx, r, values))
    while written() in (None, before):
        time.sleep(poll_s)  # leaving earlier would hold process 0 at the runtime's shutdown
    return {}


def check_settings(family: Family, env_name: str, out: Path, config, seed: int,
                   resume: bool) -> Path:
    """Refuse an unknown task, one ``family`` cannot run (``family.check_task``), and a resume
    with other settings or without the real twin's secret; then write ``loop.json``."""
    from twinrl import envs

    if env_name not in envs.names():
        raise LoopError(f"unknown task {env_name!r}; registered: {', '.join(envs.names())}")
    family.check_task(env_name, config)
    # The perturbation (a custom twin's) is not a setting the loop may read back: the twin's
    # server keeps it with the salt in eval/twin.json and refuses a resume with another one.
    rd = RunDir(out)
    settings = {"kind": "run", "env": env_name, "seed": int(seed),
                "config": report.to_jsonable(config)}
    if rd.settings.exists():
        previous = json.loads(rd.settings.read_text())
        if not resume:
            raise LoopError(f"{out} already holds a loop run; pass --resume to continue it or "
                            f"choose a new --out")
        was = _with_defaults(previous, config)
        if was != report.to_jsonable(settings):
            raise LoopError(f"--resume: {rd.settings} was started with other settings "
                            f"({_differences(was, report.to_jsonable(settings))}); resume with "
                            f"the same ones")
        # the dataset is made after the twin's server has written its secret: data without a
        # secret came from a twin that cannot be rebuilt (a new salt would be another twin)
        if rd.dataset.exists() and not rd.secret.exists():
            raise LoopError(f"--resume: {out} has no eval/twin.json (the real twin's secret; "
                            f"the run predates it or it was removed): start a new --out")
    out.mkdir(parents=True, exist_ok=True)
    report.write_json(rd.settings, settings)
    return out


def _differences(was: dict, now: dict) -> str:
    """What a resume would change, as the ``--set`` arguments that keep the run's settings (a
    default changed since the run started is the usual case), or the task and seed it ran."""
    out = [f"{k} {was.get(k)!r}, not {now.get(k)!r}" for k in ("env", "seed")
           if was.get(k) != now.get(k)]
    a, b = was.get("config") or {}, now.get("config") or {}
    keep = []
    for k in sorted(k for k in a if a[k] != b.get(k)):
        if isinstance(a[k], dict) and isinstance(b.get(k), dict):  # --set FIELD.SUB=VALUE
            keep += [f"{k}.{j}={json.dumps(v)}" for j, v in sorted(a[k].items())
                     if b[k].get(j) != v]
        else:
            keep.append(f"{k}={json.dumps(a[k])}")
    if keep:
        out.append("pass --set " + " --set ".join(keep))
    return "; ".join(out) or "loop.json differs"


def _with_defaults(previous: dict, config) -> dict:
    """``loop.json``'s settings with a setting it does not name (one a later twinrl added) at
    its default: a run started before the setting existed ran as its default does, and resumes."""
    previous = {"kind": "run", **previous}  # runs before "kind" was recorded resume too
    saved = previous.get("config")
    if not isinstance(saved, dict):
        return previous
    defaults = report.to_jsonable(type(config)())
    return {**previous, "config": {**{k: v for k, v in defaults.items() if k not in saved},
                                   **saved}}


def _start(family: Family, rd: RunDir, env_name: str, config, seed: int, progress: bool,
           perturbation) -> RunContext:
    """The family's real twin (its server creates the secret an evaluation job then reads), its
    background job and the dataset writer, in a ``RunContext``."""
    say = report.console.print if progress else quiet
    t_start = time.perf_counter()
    env, twin, writer, background = family.open(rd, env_name, config, seed, perturbation, say)
    return RunContext(env_name, int(seed), rd, config, perturbation, twin, writer,
                      Progress(rd.progress), Progress(rd.evaluation), say, progress, env,
                      t_start, background)


def _round_record(family: Family, prog: Progress, r: int) -> dict[str, Any]:
    rec = prog.record(r)
    return {"round": r, **{k: rec.get(k, dict(d) if isinstance(d, dict) else d)
                           for k, d in family.record_keys.items()}}


def _finish(family: Family, run: RunContext, rounds: list[dict[str, Any]],
            values: dict[str, Any]) -> dict[str, Any]:
    """The evaluation records merged into the rounds now that the stages are done, the family's
    figures, the final video, ``summary.json`` and the family's outputs."""
    for rec in rounds:
        rec.update(run.ev.record(rec["round"]))
    summary = {"env": run.env_name, "seed": run.seed, "config": report.to_jsonable(run.config),
               "rounds": rounds, "final": dict(rounds[-1]) if rounds else {}}
    family.summarise(run, summary)
    summary["wall_s_this_process"] = time.perf_counter() - run.t_start
    if run.config.video:
        t0 = time.perf_counter()
        summary["video"] = str(family.final_video(run, values))
        summary["video_s"] = time.perf_counter() - t0
        summary["wall_s_this_process"] = time.perf_counter() - run.t_start
    family.write_outputs(run, summary)
    return summary


# ------------------------------------------------------------------------------ helpers
def quiet(*args, **kwargs) -> None:
    """A ``say`` that says nothing (``progress=False``)."""


def read_dataset(path: Path, say=None):
    """Every intact transition of the dataset. Damage (a flipped byte, a truncated closed chunk)
    costs the records it hit, not the run: ``say`` gets one line saying what was dropped, and the
    loop goes on with the rest (a strict read would stop ``--resume`` for good)."""
    from twinrl.real import dataset as ds

    data = ds.read(path, strict=False)
    if data.problems and say is not None:
        more = f" (and {len(data.problems) - 1} more)" if len(data.problems) > 1 else ""
        say(f"  [yellow]dataset damaged, continuing with its {len(data)} intact transitions:[/] "
            f"{data.problems[0]}{more}", markup=True, highlight=False, soft_wrap=True)
    return data


def real_steps(run: RunContext) -> int:
    """Real transitions recorded so far (intact ones)."""
    return int(len(read_dataset(run.dir.dataset)))


def episodes_in(dataset_dir: Path) -> int:
    """Complete episodes in a dataset (0 when there is none yet)."""
    from twinrl.real import dataset as ds

    if not (dataset_dir / "meta.json").exists():
        return 0
    data = ds.read(dataset_dir, strict=False)  # damage is reported where the rounds read it
    return int(np.sum(data.episode_complete))


def seconds_so_far(prog: Progress, r: int, **stages: float) -> dict[str, float]:
    """Round ``r``'s wall-clock seconds per stage so far, with ``stages`` added (a resumed
    stage counts only this process's part)."""
    return {**prog.record(r).get("seconds", {}), **stages}
