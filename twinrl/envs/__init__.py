"""Tasks as Brax-compatible functional environments, and their registry.

``make(name, system=..., **overrides)`` builds a simulated task (``Env``: ``reset(rng) -> State``,
``step(state, action) -> State``, pure JAX, differentiable end to end); ``make_real(name, seed=...)``
its real twin (``twinrl.real.twin.RealTwin``, a ``gymnasium.Env`` on the MuJoCo C engine with a
hidden perturbation); ``names()`` lists the tasks. ``System`` (``envs.system``) is an identified twin
(parameters, action latency, cameras, objects) that ``make`` builds from, and
``LatencyWrapper`` (``envs.wrappers``) applies its latency. ``State`` is Brax's, so Brax's wrappers and
trainers run our tasks unmodified.

Registered tasks: ``pendulum_swingup``, ``cartpole_balance``, ``cartpole_swingup``, ``push``
(each module's docstring says what it observes, rewards and how its real twin differs).
"""

from twinrl.envs.base import Env, PerturbationSpec, State, TaskConfig, tolerance
from twinrl.envs.registry import TASKS, default_config, make, make_real, names
from twinrl.envs.system import System, randomization_fn, system_of
from twinrl.envs.wrappers import LatencyWrapper

__all__ = ["Env", "State", "TaskConfig", "PerturbationSpec", "tolerance", "make", "make_real",
           "names", "default_config", "TASKS", "System", "randomization_fn", "system_of",
           "LatencyWrapper"]
