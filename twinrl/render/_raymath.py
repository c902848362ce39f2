"""Arithmetic the ray-geometry modules share: reductions over a short last axis, guarded
square roots and divisions, a golden-section search and a line's closest approach to a segment.

Every function broadcasts over leading axes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

INF = jnp.inf
EPS = 1e-12
"""The smallest magnitude a divisor or a squared length is allowed (guards against 0)."""


# Reductions over a short last axis (xyz, the faces of a box, the geoms of a scene) are written
# out element by element: XLA on CPU then fuses them with their neighbours, where a reduce over a
# minor axis of 3 is a kernel of its own (and slow); the arithmetic is the same.
def reduce_last(op, x):
    """``op`` (binary, elementwise) folded over the last axis of ``x``, written out."""
    out = x[..., 0]
    for i in range(1, x.shape[-1]):
        out = op(out, x[..., i])
    return out


def _unrolled(op, reference):
    """The reduction ``op`` over the last axis written out, with the tangent of ``reference``
    (the ``jnp`` reduction): the reverse pass then broadcasts one cotangent instead of padding
    one per element (slices transpose to pads, which XLA on CPU does not fuse well)."""

    @jax.custom_jvp
    def f(x):
        return reduce_last(op, x)

    @f.defjvp
    def _jvp(primals, tangents):
        return f(primals[0]), jax.jvp(reference, primals, tangents)[1]

    return f


sum_last = _unrolled(jnp.add, lambda x: jnp.sum(x, -1))
max_last = _unrolled(jnp.maximum, lambda x: jnp.max(x, -1))
min_last = _unrolled(jnp.minimum, lambda x: jnp.min(x, -1))
prod_last = _unrolled(jnp.multiply, lambda x: jnp.prod(x, -1))


def dot(a, b):
    """Inner product over the last axis (``sum_last(a * b)``)."""
    return sum_last(a * b)



def safe_sqrt(x):
    """``sqrt(x)`` where ``x > 0``, else 0, with a finite gradient at and below 0."""
    return jnp.sqrt(jnp.where(x > 0, x, 1.0)) * (x > 0)


def safe_div(a, b):
    """``a / b`` with ``|b|`` held at least ``EPS`` (keeping its sign)."""
    e = jnp.asarray(EPS, jnp.result_type(b))
    return a / jnp.where(jnp.abs(b) > e, b, jnp.where(b < 0, -e, e))


def first_positive(*cands):
    """Elementwise the smallest of ``cands`` that is > 0 (``INF`` if none is)."""
    s = INF
    for c in cands:
        s = jnp.minimum(s, jnp.where(c > 0, c, INF))
    return s


def golden_min(f, lo, hi, iters: int):
    """Minimiser of a unimodal ``f`` on ``[lo, hi]`` (elementwise) by golden-section search."""
    g = 0.6180339887498949
    c, d = hi - g * (hi - lo), lo + g * (hi - lo)
    fc, fd = f(c), f(d)

    # The state travels as one stacked array, so that each iteration is one fused kernel (XLA on
    # CPU gives every output of a loop body a kernel of its own, each recomputing ``f``).
    def body(_, st):
        lo, hi, c, d, fc, fd = st
        left = fc < fd
        hi = jnp.where(left, d, hi)
        lo = jnp.where(left, lo, c)
        nc = jnp.where(left, hi - g * (hi - lo), d)
        nd = jnp.where(left, c, lo + g * (hi - lo))
        x = jnp.where(left, nc, nd)
        fx = f(x)
        fc, fd = jnp.where(left, fx, fd), jnp.where(left, fc, fx)
        return jnp.stack([lo, hi, nc, nd, fc, fd])

    st = jax.lax.fori_loop(0, iters, body, jnp.stack([lo, hi, c, d, fc, fd]))
    return 0.5 * (st[0] + st[1])


def line_segment(o, r, a, b):
    """Closest approach of the line ``o + s r`` to the segment ``[a, b]``: ``(s, distance)``.

    Exact and differentiable: for each point ``a + z (b - a)`` of the segment the best ``s`` is
    linear in ``z``, so the squared distance is quadratic in ``z``; it is minimised over
    ``z in [0, 1]``."""
    rr = dot(r, r)
    e = b - a
    s0 = dot(a - o, r) / rr  # best s for z = 0
    ds = dot(e, r) / rr  # ds/dz
    u = o + s0[..., None] * r - a  # line point minus segment point at z = 0
    v = ds[..., None] * r - e  # d(u)/dz
    z = jnp.clip(-dot(u, v) / jnp.maximum(dot(v, v), EPS), 0.0, 1.0)
    p = u + z[..., None] * v
    return s0 + ds * z, jnp.sqrt(dot(p, p) + 1e-20)
