"""Differentiable physics: MJX with a reverse-differentiable constraint solve.

``Sim`` (MJCF compiled for MJX; ``step``/``rollout``), ``PhysParams`` (identifiable parameters),
``solver`` (fixed-iteration solve), ``smooth`` (kinematics and tree sums that trace ten times
fewer equations than stock ``mjx``'s), ``gradients`` (truncation, clipping, NaN guard),
``gradcheck`` (reverse mode against central finite differences), ``mjwarn`` (MuJoCo's C warnings
as Python ``MuJoCoWarning``s, never a ``MUJOCO_LOG.TXT`` in the working directory).
"""

from twinrl.physics.mjwarn import MuJoCoWarning, mujoco_warnings
from twinrl.physics.params import PhysParams, PhysParamsError
from twinrl.physics.scenes import SCENES, scene_path
from twinrl.physics.sim import MJCFError, Sim, Trajectory, load_mjcf

__all__ = ["Sim", "PhysParams", "PhysParamsError", "Trajectory", "MJCFError", "load_mjcf", "SCENES",
           "scene_path", "MuJoCoWarning", "mujoco_warnings"]
