"""The DeepMind Control Suite as twinrl tasks: ``envs.make("dmc/cartpole-swingup")``.

Each ``dmc/<domain>-<task>`` is the suite's task on the ``dm-control`` wheel's own model
(``suite``: the XML read from the installed package, never copied), its reward rewritten in
``jax.numpy`` and checked against dm_control's own (``tests/envs/test_dmc.py``), its
initial-state distribution, observation and 1000-step episode at the suite's control timestep
(``tasks``), and a real twin (``twinrl.real.make_real``) like every task's. ``SUITE`` maps each
name to its task class and config, for ``twinrl.envs.registry``.
"""

from __future__ import annotations

from twinrl.envs.dmc.suite import SuiteTask, suite_dir, suite_xml, tolerance
from twinrl.envs.dmc.tasks import (Cartpole, CartpoleConfig, Cheetah, Finger, Pendulum, Reacher,
                                   Walker)

__all__ = ["SUITE", "SuiteTask", "suite_dir", "suite_xml", "tolerance"]

SUITE = {
    "dmc/cartpole-swingup": (Cartpole, lambda: CartpoleConfig(swingup=True)),
    "dmc/cartpole-balance": (Cartpole, lambda: CartpoleConfig(swingup=False)),
    "dmc/pendulum-swingup": (Pendulum, Pendulum.default_config),
    "dmc/reacher-easy": (Reacher, Reacher.default_config),
    "dmc/finger-spin": (Finger, Finger.default_config),
    "dmc/cheetah-run": (Cheetah, Cheetah.default_config),
    "dmc/walker-walk": (Walker, Walker.default_config),
}
"""Task name -> (task class, default config factory)."""
