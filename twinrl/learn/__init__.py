"""Learn@Sim: learning controllers through the differentiable simulator.

``trajopt`` improves an action sequence with the analytic gradient of its return (first order) or
a Gauss–Newton step (second order), accepting it only after a line search finds a better return
(PODS, Mora et al. ICML 2021, Sec. 4); the trainers (``pods``, ``hds``, ``shac``) build on it.

The names below are imported on first use (PEP 562), so ``twinrl.learn.distributed`` can join
JAX's multi-process runtime before anything starts a JAX backend (the simulator's modules build
arrays on import, and ``jax.distributed.initialize`` refuses to run after that).
"""

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # what the names are, for readers and documentation tools (no import at run time)
    from twinrl.learn.hds import HDSConfig
    from twinrl.learn.pods import PODSConfig
    from twinrl.learn.shac import SHACConfig
    from twinrl.learn.trajopt import (TrajoptConfig, TrajoptResult, env_problem, improve,
                                      optimize, trajectory_return)

_NAMES = {"TrajoptConfig": "trajopt", "TrajoptResult": "trajopt", "env_problem": "trajopt",
          "improve": "trajopt", "optimize": "trajopt", "trajectory_return": "trajopt",
          "PODSConfig": "pods", "HDSConfig": "hds", "SHACConfig": "shac"}

__all__ = ["TrajoptConfig", "TrajoptResult", "env_problem", "improve", "optimize",
           "trajectory_return", "PODSConfig", "HDSConfig", "SHACConfig"]


def __getattr__(name: str):
    if name in _NAMES:
        value = getattr(importlib.import_module(f"twinrl.learn.{_NAMES[name]}"), name)
        globals()[name] = value
        return value
    try:  # a submodule not imported yet (``twinrl.learn.shac`` after ``import twinrl.learn``)
        return importlib.import_module(f"twinrl.learn.{name}")
    except ModuleNotFoundError as e:
        if e.name != f"twinrl.learn.{name}":
            raise
    raise AttributeError(f"module 'twinrl.learn' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
