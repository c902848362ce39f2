"""The robot of the manipulation tasks: a Panda-kinematics arm, its Cartesian controller, the tool
at its flange and the camera mount (SAM-RL, Lv et al. 2023, Sec. 4: a Franka Panda does the task
while a second arm moves an RGB-D camera), and the arm tasks' ``Env``.

The names live in one module per concern, re-exported here:

- ``kinematics``: ``panda.xml`` and ``compose(task_xml)`` (the arm put into a task's scene, the
  task's ``tool`` body at its flange), forward kinematics and the Jacobian from Franka's modified
  Denavit-Hartenberg table (``DH``) in JAX, and inverse kinematics (``ik``, ``solve_ik``);
- ``controller``: ``CartesianController``, end-effector commands to joint targets by damped least
  squares, differentiable end to end;
- ``mount``: ``CameraMount``, the camera on a second arm (a workspace, a look-at point, a speed
  limit), whose pose is a differentiable input;
- ``perception``: ``ArmPerception``, the tasks' renders, image observation and target-pose fit;
- ``task``: ``ArmTask`` and ``ArmConfig``, the arm tasks' ``Env``.
"""

from twinrl.envs.arm.controller import CartesianController, check_joint_speed
from twinrl.envs.arm.kinematics import (ARM_XML, DH, DOWN, FLANGE, HOME, JOINT_RANGE, N_JOINTS,
                                        TOOL_MOUNT, compose, composed, forward_kinematics,
                                        heading, ik, jacobian, joint_frames,
                                        kinematics_and_jacobian, orientation_error, solve_ik)
from twinrl.envs.arm.mount import CameraMount
from twinrl.envs.arm.perception import ArmPerception, target_cloud
from twinrl.envs.arm.task import ARM_PERTURBATIONS, ArmConfig, ArmTask

__all__ = ["ARM_XML", "DH", "FLANGE", "HOME", "JOINT_RANGE", "compose", "forward_kinematics",
           "joint_frames", "jacobian", "kinematics_and_jacobian",
           "heading", "orientation_error", "CartesianController",
           "CameraMount", "ik", "solve_ik", "ArmTask", "ArmConfig", "DOWN"]
