"""Signed distance functions and support points of the primitives, with finite first and second
derivatives, and the contact candidates built on them.

Shared by the collision modules (``collision``: the cylinder pairs MJX searches on SDFs;
``hfield`` and ``polytopes``: a field's or a polytope's faces against a primitive's support
points, their vertices and edges against its SDF). The normal of a contact is an SDF's gradient, so reverse mode through a contact differentiates the SDF twice: every
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


NO_CONTACT = 1.0
"""Distance of a candidate that is not a contact (beyond any margin MJX allows on these pairs)."""


# Support points: ``f(pos, mat, size, n)`` -> (k, 3) the geom's deepest points along ``-n``,
# geom at ``pos`` with rotation ``mat``, all in one frame.
def sphere_support(pos, mat, size, n):
    """(1, 3) the deepest point of a sphere along ``-n`` (all in one frame)."""
    return (pos - size[0] * n)[None]


def capsule_support(pos, mat, size, n):
    """(2, 3) the deepest point of each end sphere of a capsule along ``-n``."""
    ends = jnp.array([1.0, -1.0])[:, None] * (size[1] * mat[:, 2])
    return pos + ends - size[0] * n


_CORNERS = jnp.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])


def box_support(pos, mat, size, n):
    """(8, 3) the corners of a box (the deepest, along any direction, is one of them)."""
    return pos + (_CORNERS * size) @ mat.T


def ellipsoid_support(pos, mat, size, n):
    """(1, 3) the deepest point of an ellipsoid along ``-n`` (all in one frame)."""
    u = mat.T @ -n
    # |size * u| >= min(size) > 0: the plain norm is safe
    return (pos + mat @ (size * size * u / jnp.linalg.norm(size * u)))[None]


_C120, _S120 = -0.5, 0.75 ** 0.5


def cylinder_support(pos, mat, size, n):
    """(6, 3) for each cap, the deepest point of its rim along ``-n`` and the two rim points
    at +-120 degrees from it (one frame)."""
    u = mat.T @ -n
    norm = safe_norm(u[:2])
    flat = norm < 1e-9  # axis along n: every rim point is as deep; take the cylinder's x
    radial = jnp.where(flat, jnp.array([1.0, 0.0]), u[:2] / jnp.where(flat, 1.0, norm))
    x, y = radial
    dirs = jnp.array([[x, y], [_C120 * x - _S120 * y, _S120 * x + _C120 * y],
                      [_C120 * x + _S120 * y, -_S120 * x + _C120 * y]]) * size[0]
    caps = jnp.array([1.0, -1.0]) * size[1]
    local = jnp.concatenate([jnp.concatenate([dirs, jnp.full((3, 1), z)], axis=1)
                             for z in (caps[0], caps[1])])
    return pos + local @ mat.T


def sdf_contacts(points, pos, mat, size, sdf):
    """Points (P, 3) against a geom's ``sdf`` (geom at ``pos``, rotation ``mat``, one frame):
    the SDF at each point, the position halfway into the penetration and the geom's outward
    unit normal ``g`` there (the SDF's gradient; 0 where it vanishes)."""
    local = (points - pos) @ mat  # mat.T @ (p - pos) for each row
    dist, grad = jax.vmap(jax.value_and_grad(sdf), in_axes=(0, None))(local, size)
    g = grad @ mat.T
    gn = safe_norm(g, axis=-1)[:, None]
    g = g / jnp.where(gn > 0.0, gn, 1.0)
    return dist, points - 0.5 * dist[:, None] * g, g


def edge_points(a, b, pos, mat, metric):
    """For segments ``a``-``b`` (E, 3), the point closest to a geom's centre in the geom's own
    proportions (local coordinates divided by ``metric``: an ellipsoid's semi-axes, a cylinder's
    radius and half-height), where an edge pressed into the geom pokes deepest; and whether it
    is inside the segment (an end is left to the vertex there)."""
    la = ((a - pos) @ mat) / metric
    lab = ((b - a) @ mat) / metric
    t = -jnp.sum(la * lab, axis=-1) / jnp.sum(lab * lab, axis=-1)  # |lab| > 0: a segment
    return a + jnp.clip(t, 0.0, 1.0)[:, None] * (b - a), (t > 0.0) & (t < 1.0)
