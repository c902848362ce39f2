"""The task registry: ``names()``, ``make(name, **overrides)``.

A task name maps to an ``Env`` class and its default config (``cartpole_balance`` and
``cartpole_swingup`` share a class and differ in config), in the style of MuJoCo Playground's
``default_config()`` plus flat overrides. Configs are frozen dataclasses, so no instance can
change another's defaults. A task's real twin is ``twinrl.real.make_real(name, seed=...)``: the
real side sits above ``envs`` in the package's layers (``twinrl.real`` imports ``twinrl.envs``,
never the reverse), so the registry does not reach it.

The DeepMind Control Suite's tasks are registered beside twinrl's own as ``dmc/<domain>-<task>``
(``twinrl.envs.dmc``); ``names("twinrl")`` and ``names("dmc")`` list each suite.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from twinrl.envs.arm.needle_threading import NeedleThreading
from twinrl.envs.arm.peg_insertion import PegInsertion
from twinrl.envs.arm.spatula_flipping import SpatulaFlipping
from twinrl.envs.base import Env, TaskConfig, replace_config
from twinrl.envs.cartpole import Cartpole, CartpoleConfig
from twinrl.envs.dmc import SUITE as DMC_SUITE
from twinrl.envs.pendulum import PendulumSwingup
from twinrl.envs.push import Push
from twinrl.envs.wrappers import LatencyWrapper
from twinrl.physics import PhysParams

__all__ = ["names", "make", "default_config", "TASKS", "SUITES"]


@dataclasses.dataclass(frozen=True)
class _Entry:
    env_class: type[Env]
    config: Callable[[], TaskConfig]


TASKS: dict[str, _Entry] = {
    "pendulum_swingup": _Entry(PendulumSwingup, PendulumSwingup.default_config),
    "cartpole_balance": _Entry(Cartpole, lambda: CartpoleConfig(swingup=False)),
    "cartpole_swingup": _Entry(Cartpole, lambda: CartpoleConfig(swingup=True)),
    "push": _Entry(Push, Push.default_config),
    "peg_insertion": _Entry(PegInsertion, PegInsertion.default_config),
    "spatula_flipping": _Entry(SpatulaFlipping, SpatulaFlipping.default_config),
    "needle_threading": _Entry(NeedleThreading, NeedleThreading.default_config),
    **{name: _Entry(cls, config) for name, (cls, config) in DMC_SUITE.items()},
}

SUITES = ("twinrl", "dmc")
"""The suites tasks come from: twinrl's own, and the DeepMind Control Suite's (``dmc/``)."""


def names(suite: str | None = None) -> tuple[str, ...]:
    """Registered task names: all of them, or those of ``suite`` (``"twinrl"``: twinrl's own
    tasks; ``"dmc"``: the Control Suite's, ``dmc/<domain>-<task>``)."""
    if suite is None:
        return tuple(TASKS)
    if suite not in SUITES:
        raise ValueError(f"suite must be one of {', '.join(SUITES)} or None, got {suite!r}")
    return tuple(n for n in TASKS if n.startswith("dmc/") == (suite == "dmc"))


def _entry(name: str) -> _Entry:
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; registered tasks are {', '.join(TASKS)}")
    return TASKS[name]


def default_config(name: str) -> TaskConfig:
    """The default config of task ``name`` (a fresh frozen dataclass)."""
    return _entry(name).config()


def make(name: str, *, params: PhysParams | None = None, system: Any = None,
         **overrides: Any) -> Env:
    """The simulated task ``name`` with config fields overridden, e.g.
    ``make("cartpole_swingup", episode_length=100)``; ``params`` sets its physical parameters.

    ``system`` (a ``twinrl.envs.system.System``, e.g. Real2Sim's) builds the task it describes:
    its ``params``, and its action ``latency`` applied by a ``LatencyWrapper`` (latency 0: the
    bare task). The env's ``sys`` is that system. Give ``params`` or ``system``, not both.
    """
    e = _entry(name)
    if system is None:
        return e.env_class(replace_config(e.config(), **overrides), params=params, name=name)
    # duck-typed: system.py sits above the registry (System.nominal reads TASKS)
    if not all(hasattr(system, k) for k in ("params", "latency", "task")):
        raise TypeError(f"system must be a twinrl.envs.system.System, got "
                        f"{type(system).__name__}")
    if params is not None:
        raise ValueError("give params or system, not both (a System carries its params)")
    if system.task is not None and system.task != name:
        raise ValueError(f"system was identified for task {system.task!r}, not {name!r}")
    env = e.env_class(replace_config(e.config(), **overrides), params=system.params, name=name)
    env = env.with_system(system)
    return LatencyWrapper(env, system.latency) if system.latency else env

