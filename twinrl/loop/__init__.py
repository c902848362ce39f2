"""The whole loop, Real2Sim -> Learn@Sim -> Sim2Real, in rounds, resumable: ``twinrl run``.

Hand twinrl a system it cannot see inside (a task's real twin), let it watch a few episodes, get
back a policy that works on that system. The package:

- ``engine``: ``Stage``, the round driver with its progress and resume, the settings check, the
  start and finish every run shares; a task family supplies a ``Family``;
- ``rundir``: ``RunDir``, every file and folder of a run's output directory, named once;
- ``cartpole``: the family of tasks whose observation determines their state (cartpole,
  pendulum, ...): sysid, hybrid model, learning in the identified simulator, residual, deploy
  (``LoopConfig``, ``ROUND``);
- ``arm`` (with ``arm_config`` and ``arm_stages``): SAM-RL's loop on the manipulation tasks:
  hand-eye calibration, sysid, planning, imitation, the sensing-aware Q and active deployment
  (``ArmLoopConfig``, ``ARM_ROUND``);
- ``oracle``: the oracle's training in a child process (evaluation only).

``run`` picks the family from the config (or, without one, from the task).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from twinrl.loop import engine
from twinrl.loop.cartpole import COLLECT, ROUND, LoopConfig
from twinrl.loop.engine import (Family, Progress, RunContext, Stage, episodes_in, quiet,
                                read_dataset, seconds_so_far)
from twinrl.loop.errors import LoopError
from twinrl.loop.rundir import RoundDir, RunDir

__all__ = ["LoopConfig", "run", "LoopError", "Stage", "COLLECT", "ROUND", "RunContext", "Progress",
           "check_settings", "episodes_in", "read_dataset", "quiet", "seconds_so_far", "Family",
           "RunDir", "RoundDir", "family_for"]


def family_for(env_name: str, config=None) -> Family:
    """The task family that runs ``env_name``: the one whose config class ``config`` is, else
    SAM-RL's for a manipulation task and the cartpole family's for the others."""
    from twinrl import envs
    from twinrl.loop import arm, cartpole

    for family in (cartpole.FAMILY, arm.FAMILY):
        if config is not None and isinstance(config, family.config_class):
            return family
    if config is not None:
        raise LoopError(f"no loop takes a {type(config).__name__} (LoopConfig or ArmLoopConfig)")
    if env_name in envs.names() and arm.is_arm_task(env_name):
        return arm.FAMILY
    return cartpole.FAMILY


def run(env_name: str, out: str | Path, config=None, *, seed: int = 0, resume: bool = False,
        progress: bool = True, perturbation=None) -> dict[str, Any]:
    """Run the loop on ``env_name``'s real twin (hidden perturbation drawn from ``seed``) into
    ``out``; returns the summary (also ``out/summary.json``). ``config``: a ``LoopConfig`` or,
    on a manipulation task, an ``ArmLoopConfig`` (default: the task family's defaults).

    ``perturbation`` (a ``twinrl.real.perturbation.Perturbation``) replaces the drawn one: a
    benchmark's custom real twin, e.g. one with an effect the simulator cannot model. Like the
    drawn one it is applied by the twin and never shown to the learning stages."""
    from twinrl.loop import arm, cartpole

    family = family_for(env_name, config)
    config = family.config_class() if config is None else config
    loop = arm.run if family is arm.FAMILY else cartpole.run
    return loop(env_name, out, config, seed=seed, resume=resume, progress=progress,
                perturbation=perturbation)


def check_settings(env_name: str, out: Path, config, seed: int, resume: bool) -> Path:
    """Refuse an unknown task, one ``config``'s family cannot run, and a resume with other
    settings or without the real twin's secret; then write ``loop.json``
    (``engine.check_settings``)."""
    return engine.check_settings(family_for(env_name, config), env_name, Path(out), config, seed,
                                 resume)
