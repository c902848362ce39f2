"""The scenes ``twinrl gradcheck`` checks: a bundled scene by its name, your MJCF by its path, and
a manipulation task by the task's name (its MJCF is composed, not a bundled file), with the task's
scripted expert through tool-object contact as the scenario (``ArmTask.gradcheck_scenario``)."""

from __future__ import annotations

from twinrl.physics import Sim
from twinrl.physics.scenes import Scenario


def task_scenes() -> tuple[str, ...]:
    """Tasks whose scene ``gradcheck`` takes by the task's name: the manipulation suite."""
    from twinrl.envs.arm.task import ArmTask
    from twinrl.envs.registry import TASKS

    return tuple(n for n, e in TASKS.items() if issubclass(e.env_class, ArmTask))


def load_target(target: str, *, horizon: int | None = None, seed: int = 0,
                scenario: bool = True, **sim) -> tuple[Sim, Scenario | None]:
    """``(Sim, scenario)`` for ``target``: a task of ``task_scenes()`` (its scene at the task's
    frame skip, and, with ``scenario``, the expert's window of ``horizon`` control steps, default
    30, from ``reset(seed)``), else a bundled scene's name or an MJCF path (``Sim.load``; the
    scenario None: ``gradcheck`` picks the scene's own). ``sim``: ``Sim.load``'s options
    (``iterations``, ``gradient``, ``contacts``)."""
    if target in task_scenes():
        from twinrl.envs.registry import make

        env = make(target)
        loaded = Sim.load(env.mjcf(), frame_skip=int(env.config.frame_skip), name=target, **sim)
        return loaded, (env.gradcheck_scenario(horizon or 30, seed=seed) if scenario else None)
    return Sim.load(target, **sim), None
