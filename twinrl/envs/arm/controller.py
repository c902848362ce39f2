"""The arm's Cartesian controller: an end-effector command (a displacement of the tool centre
point, plus a rotation about the vertical where the task needs it) becomes joint targets by damped
least squares on the arm's Jacobian, with the tool axis pulled towards the task's nominal direction
and a null-space pull towards the home posture. Differentiable end to end, so the gradient of a
return w.r.t. end-effector actions goes through the controller, the servos, the arm and the
contacts."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.envs.arm.kinematics import (DOWN, HOME, JOINT_RANGE, N_JOINTS, heading,
                                        kinematics_and_jacobian, null_space, orientation_error,
                                        rot_z)


@dataclasses.dataclass(frozen=True)
class CartesianController:
    """End-effector command -> joint position targets (damped least squares).

    Action layout: ``[dx, dy, dz]`` in [-1, 1] (times ``max_step`` metres per control step), and,
    with ``yaw=True``, a fourth entry: rotation about the vertical (times ``max_yaw`` rad per step).
    The tool's orientation is pulled towards ``nominal`` turned about the vertical by its current
    heading (plus the commanded turn) with gain ``tilt_gain`` each step, so the tool stays level
    without the policy spending actions on it.
    """

    tcp: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The controlled point in the tool frame (the peg's tip, the blade's edge, the thread's
    end)."""
    nominal: tuple = DOWN
    """The tool's nominal orientation (rows of a world rotation matrix) at heading 0."""
    yaw: bool = False
    """Whether the action has a fourth entry turning the tool about the vertical."""
    max_step: float = 0.02
    """Metres per control step at |action| = 1."""
    max_yaw: float = 0.1
    """Radians per control step at |action| = 1."""
    tilt_gain: float = 0.5
    """Fraction of the tool's orientation error corrected per step."""
    damping: float = 0.05
    """Damped-least-squares damping (lambda, in the 6-D task space's units)."""
    posture_gain: float = 0.1
    """Null-space pull towards ``posture`` per step (fraction of the joint error)."""
    posture: tuple = tuple(HOME)
    """The joint posture the null space is pulled towards (the task's start posture)."""
    joint_speed: tuple | None = None
    """Per joint, how fast its servo closes a step of its target relative to the nominal arm's
    (gain over damping, over the MJCF's: ``ArmTask.servo_speed``), as identified; each joint's step
    is divided by it, so the tool moves as commanded whatever the servos (None: the nominal
    arm's, all ones). The targets are set from the measured joints, so a servo 30 % faster
    than nominal moves its joint 30 % further per step and bends the commanded direction
    (``bench/arm_controller.py`` (in git history))."""

    @property
    def action_size(self) -> int:
        return 4 if self.yaw else 3

    def __call__(self, q: jax.Array, action: jax.Array) -> jax.Array:
        """Joint targets (7,) for measured joint angles ``q`` (7,) and ``action`` (clipped)."""
        a = jnp.clip(action, -1.0, 1.0)
        _, R, J = kinematics_and_jacobian(q, self.tcp)
        turn = a[3] * self.max_yaw if self.yaw else jnp.zeros((), q.dtype)
        R_des = rot_z(heading(R, self.nominal) + turn) @ jnp.asarray(self.nominal, q.dtype)
        dx = jnp.concatenate([self.max_step * a[:3],
                              self.tilt_gain * orientation_error(R, R_des)])
        if self.yaw:  # the commanded turn itself, not a fraction of it
            dx = dx.at[5].add((1.0 - self.tilt_gain) * turn)
        JJt = J @ J.T + self.damping ** 2 * jnp.eye(6, dtype=q.dtype)
        pinv = J.T @ jnp.linalg.solve(JJt, jnp.eye(6, dtype=q.dtype))
        posture = jnp.asarray(self.posture, q.dtype)
        dq = pinv @ dx + null_space(J) @ (self.posture_gain * (posture - q))
        if self.joint_speed is not None:
            dq = dq / jnp.asarray(self.joint_speed, q.dtype)
        lo, hi = (jnp.asarray(JOINT_RANGE[:, i], q.dtype) for i in (0, 1))
        return jnp.clip(q + dq, lo, hi)


def check_joint_speed(joint_speed) -> tuple[float, ...] | None:
    """``joint_speed`` (``CartesianController.joint_speed``) as 7 positive finite floats, or
    None; anything else raises one line naming it."""
    if joint_speed is None:
        return None
    js = np.asarray(joint_speed, np.float64).reshape(-1)
    if js.shape != (N_JOINTS,) or not np.all(np.isfinite(js)) or np.any(js <= 0):
        raise ValueError(f"joint_speed must be {N_JOINTS} positive finite numbers (each servo's "
                         f"speed relative to the nominal arm's), got {np.asarray(joint_speed)!r}")
    return tuple(float(x) for x in js)
