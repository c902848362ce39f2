"""Convex polyhedra against rays: boxes' closest approach and depth (exact, no search), the
depth of a ray in any convex polytope, and ray-triangle hits for meshes.

Outside a convex polytope a line passes closest to one of its edges; inside, its deepest point is
where two face planes of opposite slope cross. Both are solved in closed form, so values and
gradients are exact (``primitives`` gives the module's conventions).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from twinrl.render._raymath import EPS, INF, dot, line_segment


def _edges_closest(o, r, a, b):
    """Closest approach of the line to the nearest of the segments ``a``, ``b`` (..., E, 3)."""
    s, d = line_segment(o[..., None, :], r[..., None, :], a, b)
    k = jnp.argmin(d, -1)
    pick = lambda x: jnp.take_along_axis(x, k[..., None], -1)[..., 0]  # noqa: E731
    return pick(s), pick(d)


def _box_edge_table():
    """The 12 edges of the box ``[-1, 1]^3`` as NumPy endpoints ``a``, ``b`` (12, 3) each."""
    import itertools

    import numpy as np

    a, b = [], []
    for axis in range(3):
        others = [i for i in range(3) if i != axis]
        for s1, s2 in itertools.product((-1.0, 1.0), repeat=2):
            lo = np.zeros(3)
            lo[others[0]], lo[others[1]], lo[axis] = s1, s2, -1.0
            hi = lo.copy()
            hi[axis] = 1.0
            a.append(lo)
            b.append(hi)
    return np.array(a), np.array(b)


def polyhedral_depth(m, c, s0):
    """Deepest point of a ray inside a convex polytope ``max_k (m_k s + c_k) <= 0``.

    ``s0`` (found by search, held constant) locates the minimum of the max of the linear pieces;
    there two pieces of opposite slope cross, and the crossing is solved exactly, so the value's
    gradient is right (the envelope theorem does not hold at such a kink). Pieces not in play are
    ``-inf``. Returns the value ``min_s max_k (m_k s + c_k)`` (negative inside)."""
    v = m * s0[..., None] + c
    top2 = jax.lax.top_k(jax.lax.stop_gradient(v), 2)[1]
    ma, mb = (jnp.take_along_axis(m, top2[..., i:i + 1], -1)[..., 0] for i in (0, 1))
    ca, cb = (jnp.take_along_axis(c, top2[..., i:i + 1], -1)[..., 0] for i in (0, 1))
    kink = (ma * mb < 0) & jnp.isfinite(cb)
    s = jnp.where(kink, (cb - ca) / jnp.where(kink, ma - mb, 1.0), s0)
    return jnp.where(kink, ma * s + ca, ma * s0 + ca)


def _broadcast(*xs):
    """Arrays broadcast to one shape up front: a small operand (a geom's size) broadcast
    implicitly in every operation gets one reduction per use in the reverse pass; broadcast once,
    its cotangents add elementwise and are reduced once."""
    shape = jnp.broadcast_shapes(*(x.shape for x in xs))
    return tuple(jnp.broadcast_to(x, shape) for x in xs)


def _onehot_pick(x, k, n):
    """``x[..., k]`` for an integer array ``k`` (``x`` (..., n) or (n,)) as a masked sum: under XLA
    on CPU it fuses, where ``take_along_axis`` is a gather (and its transpose a scatter)."""
    return jnp.sum(jnp.where(k[..., None] == jnp.arange(n), x, 0.0), -1)


def _box_edges_closest(o, r, size):
    """``_edges_closest`` over the box's 12 edges (``_box_edge_table`` times ``size``): the
    nearest edge is found without gradients (per coordinate, with no minor axis of 3 or 12), then
    only its ``line_segment`` is differentiated: the same values and gradients as differentiating
    all 12 and picking one, without 12 edges' worth of reverse pass."""
    o_, r_, h_ = (jax.lax.stop_gradient(x) for x in _broadcast(o, r, size))
    o_, r_, h_ = ([x[..., i] for i in range(3)] for x in (o_, r_, h_))
    ta, tb = _box_edge_table()
    te = tb - ta
    rr = r_[0] * r_[0] + r_[1] * r_[1] + r_[2] * r_[2]
    irr = 1.0 / rr
    ta_, te_ = jnp.asarray(ta, size.dtype), jnp.asarray(te, size.dtype)

    # a loop, not an unrolled chain of selects: XLA on CPU splits a long unrolled chain into
    # fusions that each recompute most of it
    def edge(k, best):
        best_k, best_d = best
        a = [ta_[k, i] * h_[i] for i in range(3)]
        e = [te_[k, i] * h_[i] for i in range(3)]
        s0 = ((a[0] - o_[0]) * r_[0] + (a[1] - o_[1]) * r_[1] + (a[2] - o_[2]) * r_[2]) * irr
        ds = (e[0] * r_[0] + e[1] * r_[1] + e[2] * r_[2]) * irr
        u = [o_[i] + s0 * r_[i] - a[i] for i in range(3)]
        v = [ds * r_[i] - e[i] for i in range(3)]
        vv = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
        uv = u[0] * v[0] + u[1] * v[1] + u[2] * v[2]
        z = jnp.clip(-uv / jnp.maximum(vv, EPS), 0.0, 1.0)
        d = (u[0] + z * v[0]) ** 2 + (u[1] + z * v[1]) ** 2 + (u[2] + z * v[2]) ** 2
        better = d < best_d
        return jnp.where(better, k, best_k), jnp.where(better, d, best_d)

    best_k, _ = jax.lax.fori_loop(0, 12, edge, (jnp.zeros(rr.shape, jnp.int32),
                                                jnp.full(rr.shape, INF, rr.dtype)))
    a = ta_[best_k] * size  # a gather from a constant table: nothing to differentiate
    e = te_[best_k] * size
    return line_segment(o, r, a, a + e)


def box_depth(o, r, size):
    """Deepest point of the line ``o + s r`` in a box: ``(s, min_s max_i (|o_i + s r_i| -
    size_i))``, exact (no search).

    Per axis ``|o_i + s r_i| - size_i`` is a rising piece (slope ``|r_i|``) and a falling one;
    the minimum of their maximum lies where a rising piece ``i`` meets a falling piece ``j``, and
    its value is the largest of those 9 crossings (a 1-D linear programme is decided by two
    constraints). The active pair is found without gradients and its crossing then solved
    differentiably, as in ``polyhedral_depth``; ``s`` is held constant (as a search result
    would be)."""
    sg = jnp.where(r >= 0, 1.0, -1.0).astype(r.dtype)
    A = sg * r  # slopes |r_i|
    P = sg * o - size  # rising pieces' intercepts
    Q = -sg * o - size  # falling pieces' intercepts
    A_, P_, Q_ = ([jax.lax.stop_gradient(x[..., i]) for i in range(3)] for x in (A, P, Q))
    best_v, best_s, bi, bj = None, None, None, None
    for i in range(3):
        for j in range(3):
            den = A_[i] + A_[j]
            ok = den > 0
            den = jnp.where(ok, den, 1.0)
            v = jnp.where(ok, (A_[i] * Q_[j] + A_[j] * P_[i]) / den, -INF)
            s = (Q_[j] - P_[i]) / den
            if best_v is None:
                best_v, best_s = v, s
                bi, bj = jnp.zeros(v.shape, jnp.int32), jnp.zeros(v.shape, jnp.int32)
            else:
                better = v > best_v
                best_v, best_s = jnp.where(better, v, best_v), jnp.where(better, s, best_s)
                bi, bj = jnp.where(better, i, bi), jnp.where(better, j, bj)
    Ai, Pi = _onehot_pick(A, bi, 3), _onehot_pick(P, bi, 3)
    Aj, Qj = _onehot_pick(A, bj, 3), _onehot_pick(Q, bj, 3)
    v = (Ai * Qj + Aj * Pi) / (Ai + Aj)
    return best_s, v


def closest_box(o, r, size, iters=16):
    """Outside: the nearest edge (a line missing a convex polytope passes closest to one of its
    edges), exact and differentiable in ``s`` too. Inside: the deepest point of the ray, exact
    (``box_depth``)."""
    s_out, d_out = _box_edges_closest(o, r, size)
    s_in, d_in = box_depth(o, r, size)
    inside = d_in < 0
    return jnp.where(inside, s_in, s_out), jnp.where(inside, d_in, d_out)



# ------------------------------------------------------------------ triangle meshes (world frame)
def hit_triangles(o, r, v0, v1, v2):
    """Moller-Trumbore, double-sided: ``s`` of the ray hitting each triangle (``inf`` if none).
    ``o`` (3,), ``r`` (..., 1, 3), triangles (T, 3) -> (..., T)."""
    e1, e2 = v1 - v0, v2 - v0
    pv = jnp.cross(r, e2)
    det = dot(e1, pv)
    inv = 1.0 / jnp.where(jnp.abs(det) > 1e-15, det, 1e-15)
    tv = o - v0
    u = dot(tv, pv) * inv
    qv = jnp.cross(tv, e1)
    v = dot(r, qv) * inv
    s = dot(e2, qv) * inv
    ok = (jnp.abs(det) > 1e-15) & (u >= 0) & (v >= 0) & (u + v <= 1) & (s > 0)
    return jnp.where(ok, s, INF)
