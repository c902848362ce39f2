"""Rotations as ``(w, x, y, z)`` quaternions, in JAX (differentiable) and NumPy.

The physics' kinematic chains (``twinrl.physics.chain``), the renderer's cameras and the arm's
camera mount all compose rotations; this module is their one home, in the lowest layer, so that
nothing below the renderer has to import it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["quat_to_mat", "mat_to_quat", "quat_mul", "rotvec_to_quat"]


def quat_to_mat(q: jax.Array) -> jax.Array:
    """Rotation matrix of a quaternion ``(w, x, y, z)`` (normalised first, so any non-zero
    4-vector is a valid parameterisation and gradients stay tangent)."""
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def mat_to_quat(m) -> np.ndarray:
    """Quaternion ``(w, x, y, z)`` of a rotation matrix (NumPy; for construction, not for AD)."""
    import mujoco

    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.asarray(m, np.float64).reshape(9))
    return q


def quat_mul(a: jax.Array, b: jax.Array) -> jax.Array:
    """Hamilton product ``a * b`` of ``(w, x, y, z)`` quaternions."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return jnp.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def rotvec_to_quat(v: jax.Array) -> jax.Array:
    """Quaternion of an axis-angle vector (smooth at 0: the gradient at v = 0 is exact)."""
    th2 = jnp.sum(v * v, -1, keepdims=True)
    th = jnp.sqrt(jnp.where(th2 > 1e-12, th2, 1.0))
    small = th2 <= 1e-12
    half_sinc = jnp.where(small, 0.5 - th2 / 48.0, jnp.sin(0.5 * th) / th)
    w = jnp.where(small, 1.0 - th2 / 8.0, jnp.cos(0.5 * th))
    return jnp.concatenate([w, half_sinc * v], -1)
