"""Learn@Sim: learning controllers through the differentiable simulator.

``trajopt`` improves an action sequence with the analytic gradient of its return (first order) or
a Gauss–Newton step (second order), accepting it only after a line search finds a better return
(PODS, Mora et al. ICML 2021, Sec. 4); the trainers (``pods``, ``hds``, ``shac``) build on it.
"""

from twinrl.learn.trajopt import (TrajoptConfig, TrajoptResult, env_problem, improve, optimize,
                                  trajectory_return)
from twinrl.learn.pods import PODSConfig  # noqa: E402  (after trajopt, which pods imports)
from twinrl.learn.hds import HDSConfig  # noqa: E402
from twinrl.learn.shac import SHACConfig  # noqa: E402

__all__ = ["TrajoptConfig", "TrajoptResult", "env_problem", "improve", "optimize",
           "trajectory_return", "PODSConfig", "HDSConfig", "SHACConfig"]
