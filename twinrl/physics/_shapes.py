"""Signed distance functions of the smooth primitives, with finite first and second derivatives.

Shared by the collision modules (``collision``: the cylinder pairs MJX searches on SDFs;
``hfield``: height-field vertices against a cylinder or an ellipsoid). The normal of a contact
is an SDF's gradient, so reverse mode through a contact differentiates the SDF twice: every
square root here is guarded at 0 (a double ``where``), where the plain one's derivative is
``inf`` and gives NaN.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def safe_norm(x: jax.Array, axis: int | None = None) -> jax.Array:
    """|x| (over ``axis``; all of ``x`` if None) with finite first and second derivatives at 0."""
    sq = jnp.sum(x * x, axis=axis)
    zero = sq == 0.0
    return jnp.where(zero, 0.0, jnp.sqrt(jnp.where(zero, 1.0, sq)))


def cylinder_sdf(pos: jax.Array, size: jax.Array) -> jax.Array:
    """Signed distance to a cylinder of radius ``size[0]``, half-height ``size[1]`` along z.

    The same function as MJX's ``_cylinder``, written so that reverse mode of its gradient
    (the contact normal) stays finite on the axis and inside the shape."""
    a0 = safe_norm(pos[:2]) - size[0]
    a1 = jnp.abs(pos[2]) - size[1]
    outside = safe_norm(jnp.stack([jnp.maximum(a0, 0.0), jnp.maximum(a1, 0.0)]))
    return jnp.minimum(jnp.maximum(a0, a1), 0.0) + outside


def ellipsoid_sdf(pos: jax.Array, size: jax.Array) -> jax.Array:
    """Approximate signed distance to an ellipsoid of semi-axes ``size`` (MJX's ``_ellipsoid``:
    ``k0 (k0 - 1) / k1`` with ``k0 = |pos / size|``, ``k1 = |pos / size^2|``; exact on the
    surface, where its gradient is the surface normal), guarded at the centre."""
    k0 = safe_norm(pos / size)
    k1 = safe_norm(pos / (size * size))
    small = k1 < 1e-12
    return jnp.where(small, -jnp.min(size), k0 * (k0 - 1.0) / jnp.where(small, 1.0, k1))


def sphere_sdf(pos: jax.Array, size: jax.Array) -> jax.Array:
    """Signed distance to a sphere of radius ``size[0]``."""
    return safe_norm(pos) - size[0]


def capsule_sdf(pos: jax.Array, size: jax.Array) -> jax.Array:
    """Signed distance to a capsule of radius ``size[0]``, half-length ``size[1]`` along z."""
    axis = jnp.clip(pos[2], -size[1], size[1])
    return safe_norm(pos - jnp.array([0.0, 0.0, 1.0]) * axis) - size[0]


def box_sdf(pos: jax.Array, size: jax.Array) -> jax.Array:
    """Signed distance to a box of half-sizes ``size``."""
    q = jnp.abs(pos) - size
    return safe_norm(jnp.maximum(q, 0.0)) + jnp.minimum(jnp.max(q), 0.0)
