"""twinrl: robot learning through differentiable digital twins (Real2Sim -> Learn@Sim -> Sim2Real).

``import twinrl`` applies the JAX settings (``twinrl.jaxconfig``) and gives every sub-package as
an attribute (``twinrl.envs``, ``twinrl.physics``, ...), imported on first use (PEP 562), so a
command that needs only the physics does not pay for the learners' imports.

It also registers every task's real twin with Gymnasium as ``twinrl/<task>-real-v0``
(``gymnasium.make("twinrl/push-real-v0", seed=3)`` is ``twinrl.real.make_real("push", seed=3)``;
keyword arguments are ``RealTwin``'s), so Gymnasium tooling (Stable-Baselines, CleanRL scripts,
``gymnasium.make_vec``) takes them by id. The twin truncates its own episodes at the task's
length, and Gymnasium's passive checker is off (its warnings about the unbounded velocity boxes
would print on every ``make``).
"""

import importlib

from twinrl import jaxconfig

jaxconfig.set_cpu_flags()
jaxconfig.enable_compilation_cache()
jaxconfig.import_mjx_quietly()

__version__ = "0.1.0"

TASK_NAMES = ("pendulum_swingup", "cartpole_balance", "cartpole_swingup", "push", "peg_insertion",
              "spatula_flipping", "needle_threading")
"""``twinrl.envs.names("twinrl")`` (twinrl's own tasks, each registered with Gymnasium as
``twinrl/<task>-real-v0``) without importing the tasks (a test keeps the two equal)."""


def _register_gymnasium() -> None:
    import gymnasium

    for task in TASK_NAMES:
        env_id = f"twinrl/{task}-real-v0"
        if env_id not in gymnasium.registry:
            gymnasium.register(env_id, entry_point="twinrl.real.twin:RealTwin",
                               kwargs={"task": task}, disable_env_checker=True)


_register_gymnasium()

_SUBMODULES = ("envs", "eval", "learn", "loop", "physics", "real", "real2sim", "render", "report",
               "sim2real", "cli")


def __getattr__(name: str):
    if name in _SUBMODULES:
        return importlib.import_module(f"twinrl.{name}")  # also sets it as an attribute
    raise AttributeError(f"module 'twinrl' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_SUBMODULES))
