"""Tasks as Brax-compatible functional environments, and their registry.

``make(name, system=..., **overrides)`` builds a simulated task (``Env``: ``reset(rng) -> State``,
``step(state, action) -> State``, pure JAX, differentiable end to end); ``names()`` lists the
tasks. A task's real twin is ``twinrl.real.make_real(name, seed=...)`` (a ``gymnasium.Env`` on the
MuJoCo C engine with a hidden perturbation): ``real`` builds on ``envs``, not the other way.
``System`` (``envs.system``) is an identified twin (parameters, action latency, cameras, objects,
the tool's grasp, the controller's calibration) that ``make`` builds from (``Env.with_system``),
and ``LatencyWrapper`` (``envs.wrappers``) applies its latency. ``State`` is Brax's, so Brax's
wrappers and trainers run our tasks unmodified.

Registered tasks: ``pendulum_swingup``, ``cartpole_balance``, ``cartpole_swingup``, ``push``
(each module's docstring says what it observes, rewards and how its real twin differs), and the
manipulation suite (``envs.arm``); and the DeepMind Control Suite's tasks on the ``dm-control``
wheel's own models, ``dmc/<domain>-<task>`` (``envs.dmc``; ``names("dmc")``).
``from_mjcf(path)`` (``envs.mjcf``) makes your own robot's MJCF a task observing its full state,
for Real2Sim on your logs.
"""

from twinrl.envs.base import Env, PerturbationSpec, State, TaskConfig, tolerance
from twinrl.envs.registry import TASKS, default_config, make, names
from twinrl.envs.system import (ControllerCalibration, System, ToolGrasp, randomization_fn,
                                 system_of)
from twinrl.envs.wrappers import LatencyWrapper
from twinrl.envs.mjcf import MJCFTask, from_mjcf

__all__ = ["Env", "State", "TaskConfig", "PerturbationSpec", "tolerance", "make", "names",
           "default_config", "TASKS", "System", "randomization_fn", "system_of", "LatencyWrapper",
           "MJCFTask", "from_mjcf", "ToolGrasp", "ControllerCalibration"]
