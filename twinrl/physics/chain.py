"""World poses of a few geoms from the joints of their own kinematic chain only.

``mjx.kinematics`` computes every body of a model; tracing it costs about 1.5 s of Python per call
for the Panda tasks (2 cores), and a model-based pose fit that calls it inside ``jacfwd`` and
restarts (``ArmTask.fit_target_pose``) traced it six times: 10-18 s before XLA saw anything, for
every function that renders an image observation (the persistent compilation cache saves
compiles, never traces). ``GeomChain`` walks only the bodies from the world to the geoms' body,
with MuJoCo's own rules (``mj_kinematics``: a body's frame from its parent's and its
``body_pos``/``body_quat``, then each joint in order -- a slide moves along its axis, a hinge
rotates about its axis through its anchor, both by ``qpos - qpos0``), reading the body and geom
frames from the ``mjx.Model`` it is given, so identified parameters reach it. It traces in
milliseconds and equals ``mjx.kinematics`` (``tests/physics/test_chain.py``). Free and ball
joints are not handled: ``GeomChain.supports`` says so and callers keep ``mjx.kinematics``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from twinrl.physics.rotations import quat_mul, quat_to_mat, rotvec_to_quat

__all__ = ["GeomChain"]

_SLIDE, _HINGE = int(mujoco.mjtJoint.mjJNT_SLIDE), int(mujoco.mjtJoint.mjJNT_HINGE)


class GeomChain:
    """Poses of the geoms ``geom_ids`` of a MuJoCo model from ``qpos`` (module docstring).

    Args:
      mj_model: the ``mujoco.MjModel`` (structure: parents, joints, types; NumPy).
      geom_ids: the geoms, all on one body.
    """

    def __init__(self, mj_model: mujoco.MjModel, geom_ids):
        self.geom_ids = np.asarray(geom_ids, int)
        bodies = np.unique(np.asarray(mj_model.geom_bodyid)[self.geom_ids])
        if bodies.size != 1:
            raise ValueError(f"GeomChain: geoms {self.geom_ids.tolist()} are on bodies "
                             f"{bodies.tolist()}; they must share one")
        chain, b = [], int(bodies[0])
        while b != 0:
            chain.append(b)
            b = int(mj_model.body_parentid[b])
        self.bodies = chain[::-1]  # world's child first
        jb = np.asarray(mj_model.jnt_bodyid)
        self.joints = [np.flatnonzero(jb == b).tolist() for b in self.bodies]
        types = np.asarray(mj_model.jnt_type)
        self.supports = all(int(types[j]) in (_SLIDE, _HINGE) for js in self.joints for j in js)
        self._types = types
        self._qadr = np.asarray(mj_model.jnt_qposadr)
        self._qpos0 = np.asarray(mj_model.qpos0)

    @property
    def qpos_indices(self) -> np.ndarray:
        """The ``qpos`` entries the poses depend on."""
        return np.asarray([self._qadr[j] for js in self.joints for j in js], int)

    def __call__(self, model, qpos) -> tuple[jax.Array, jax.Array]:
        """``(xpos (G, 3), xmat (G, 3, 3))`` of the geoms at ``qpos`` (the full ``qpos``, or any
        array indexable by ``qpos_indices``); ``model`` an ``mjx.Model``."""
        if not self.supports:
            raise ValueError("GeomChain handles slide and hinge joints only (module docstring)")
        dt = jnp.result_type(qpos)
        pos, quat = jnp.zeros(3, dt), jnp.asarray([1.0, 0.0, 0.0, 0.0], dt)
        for b, js in zip(self.bodies, self.joints):
            pos = pos + quat_to_mat(quat) @ jnp.asarray(model.body_pos[b], dt)
            quat = quat_mul(quat, jnp.asarray(model.body_quat[b], dt))
            for j in js:
                a = int(self._qadr[j])
                angle = qpos[a] - jnp.asarray(self._qpos0[a], dt)
                axis = jnp.asarray(model.jnt_axis[j], dt)
                if int(self._types[j]) == _SLIDE:
                    pos = pos + quat_to_mat(quat) @ axis * angle
                else:
                    anchor = pos + quat_to_mat(quat) @ jnp.asarray(model.jnt_pos[j], dt)
                    quat = quat_mul(quat, rotvec_to_quat(axis * angle))
                    pos = anchor - quat_to_mat(quat) @ jnp.asarray(model.jnt_pos[j], dt)
            quat = quat / jnp.linalg.norm(quat)
        gp = jnp.asarray(model.geom_pos[self.geom_ids], dt)
        gq = jnp.asarray(model.geom_quat[self.geom_ids], dt)
        return pos + gp @ quat_to_mat(quat).T, quat_to_mat(quat_mul(quat, gq))
