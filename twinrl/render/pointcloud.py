"""Point clouds from depth images and the distances between them (SAM-RL, Sec. 3.2: the
point-cloud term of its visual Real2Sim loss).

Clouds have a fixed size so everything jits: a cloud is ``points`` (N, 3) with ``weights`` (N,)
(0 for pixels that are masked out: background, other objects, or outside a soft mask). Both losses
are differentiable in the points and the weights.

- ``chamfer``: weighted mean squared nearest-neighbour distance, both ways.
- ``sinkhorn_emd``: the entropy-regularised optimal-transport (earth mover's) cost, with ott-jax
  0.6.0's Sinkhorn solver (gradients by Danskin's theorem at the optimal
  potentials).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from twinrl.jaxconfig import exact_matmuls
from twinrl.render.camera import Camera

__all__ = ["depth_to_points", "chamfer", "sinkhorn_emd", "subsample"]


@exact_matmuls
def depth_to_points(camera: Camera, depth: jax.Array, mask: jax.Array | None = None,
                    *, far: float | None = None) -> tuple[jax.Array, jax.Array]:
    """World-frame points (H*W, 3) of a depth image (H, W) (metres along the viewing axis, as
    ``mujoco.Renderer`` and ``Renderer.render`` give it) seen from ``camera``, and their weights
    (H*W,): ``mask`` (bool or soft, (H, W)) if given, times ``depth < far`` if ``far`` is given."""
    depth = jnp.asarray(depth)
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth has shape {depth.shape}; the camera's image is "
                         f"{(camera.height, camera.width)}")
    o, r = camera.rays()
    pts = o + depth[..., None] * r
    w = jnp.ones(depth.shape, pts.dtype)
    if mask is not None:
        mask = jnp.asarray(mask)
        if mask.shape != depth.shape:
            raise ValueError(f"mask has shape {mask.shape}, depth {depth.shape}")
        w = w * mask.astype(pts.dtype)
    if far is not None:
        w = w * (depth < 0.999 * far)
    return pts.reshape(-1, 3), w.reshape(-1)


def subsample(points: jax.Array, weights: jax.Array, n: int, key: jax.Array):
    """``n`` points drawn without replacement (uniformly among positive weights first; a fixed
    size for jit). Use a fixed key across optimisation steps so the loss stays smooth."""
    p = jnp.where(weights > 0, 1.0, 1e-9)
    idx = jax.random.choice(key, points.shape[0], (n,), replace=False, p=p / p.sum())
    return points[idx], weights[idx]


def _check(a, wa, name):
    a = jnp.asarray(a)
    if a.ndim != 2 or a.shape[-1] != 3:
        raise ValueError(f"{name} must be (N, 3) points, got shape {a.shape}")
    wa = jnp.ones(a.shape[0], a.dtype) if wa is None else jnp.asarray(wa, a.dtype)
    if wa.shape != a.shape[:1]:
        raise ValueError(f"weights of {name} must be ({a.shape[0]},), got {wa.shape}")
    return a, wa


def chamfer(a: jax.Array, b: jax.Array, wa: jax.Array | None = None,
            wb: jax.Array | None = None) -> jax.Array:
    """Symmetric Chamfer distance: weighted mean over ``a`` of the squared distance to the
    nearest (positively weighted) point of ``b``, plus the same from ``b`` to ``a``."""
    a, wa = _check(a, wa, "a")
    b, wb = _check(b, wb, "b")
    d2 = jnp.sum((a[:, None, :] - b[None, :, :]) ** 2, -1)
    big = jnp.asarray(1e12, d2.dtype)
    ab = jnp.min(jnp.where(wb[None, :] > 0, d2, big), 1)
    ba = jnp.min(jnp.where(wa[:, None] > 0, d2, big), 0)
    return (jnp.sum(wa * ab) / jnp.maximum(jnp.sum(wa), 1e-12)
            + jnp.sum(wb * ba) / jnp.maximum(jnp.sum(wb), 1e-12))


@exact_matmuls
def sinkhorn_emd(a: jax.Array, b: jax.Array, wa: jax.Array | None = None,
                 wb: jax.Array | None = None, *, epsilon: float = 1e-4,
                 max_iterations: int = 200, debiased: bool = True) -> jax.Array:
    """Entropy-regularised earth mover's distance (squared Euclidean ground cost, m^2) between
    two weighted clouds (weights normalised to unit mass), by ott-jax's Sinkhorn solver.

    Args:
      epsilon: entropic regularisation (m^2); about (spacing between points)^2 or smaller.
      max_iterations: Sinkhorn iterations at most (a fixed bound keeps it jit-able).
      debiased: the Sinkhorn divergence ``OT(a, b) - (OT(a, a) + OT(b, b)) / 2``, zero for
        identical clouds (the entropic term otherwise biases fits towards shrinking clouds).
    """
    from ott.geometry import pointcloud
    from ott.problems.linear import linear_problem
    from ott.solvers.linear import sinkhorn

    a, wa = _check(a, wa, "a")
    b, wb = _check(b, wb, "b")
    # a tiny floor keeps every marginal positive, so masked-out points carry no mass but no NaN
    wa = jnp.maximum(wa, 0.0) + 1e-9
    wb = jnp.maximum(wb, 0.0) + 1e-9
    wa, wb = wa / wa.sum(), wb / wb.sum()
    # Danskin's theorem: the gradient of the regularised cost is that of the cost at the optimal
    # potentials, so no implicit linear solve (ill-conditioned at small epsilon) is needed.
    solver = sinkhorn.Sinkhorn(max_iterations=max_iterations, threshold=1e-6, implicit_diff=None,
                               use_danskin=True)

    def ot(x, y, wx, wy):
        geom = pointcloud.PointCloud(x, y, epsilon=epsilon)
        return solver(linear_problem.LinearProblem(geom, wx, wy)).reg_ot_cost

    cost = ot(a, b, wa, wb)
    if debiased:
        cost = cost - 0.5 * (ot(a, a, wa, wa) + ot(b, b, wb, wb))
    return cost


def huber_residual(r, c):
    """Residual whose square is twice the Huber loss of ``r`` (scale ``c``): linear tails (a
    robust least-squares residual for point-to-surface fits)."""
    a = jnp.abs(r)
    tail = a > c  # there 2ca - c^2 > c^2: the square root's argument is kept off 0 elsewhere,
    # where its infinite slope times the unused branch's zero would make the gradient NaN
    return jnp.where(tail, jnp.sign(r) * jnp.sqrt(jnp.where(tail, 2.0 * c * a - c * c, 1.0)), r)
