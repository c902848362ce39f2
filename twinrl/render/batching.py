"""A render under every transformation: drawn by the C++ kernel where there is one, else by the
JAX renderer, and a ``jax.vmap``-ed batch drawn a chunk of cameras at a time (so that its arrays
stay in the CPU's caches); the JVP is the JAX renderer's, whose reverse mode is the kernel's
reverse pass. ``render_jit`` is the compiled form ``Renderer.render`` calls outside ``jit``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from twinrl.render import linear
from twinrl.render.image import render_jax
from twinrl.render.kernel import pullback_native, render_native

BATCH_ELEMENTS = 2 ** 18
"""How many (pixel, surface) pairs a batched render (``jax.vmap`` over cameras or scenes) works
on at once, at most: a larger batch is drawn in chunks of cameras (``Renderer.batch_chunk``), so
that each operation's arrays stay in the CPU's caches. Batch 16, 2 CPU cores: peg insertion's
15 geoms (61k pairs a 64x64 frame) drawn 4 cameras at a time instead of all 16 at once, 1.3x
faster hard and soft (1.8x / 1.3x at 128x128); push's 4 geoms (16k pairs a frame) stay one batch
at 64x64 (``bench/render.py``)."""


def batch_chunk(R, height: int, width: int, batch: int) -> int:
    """How many cameras of a batch of ``batch`` a ``jax.vmap``-ed render draws at once: the
    largest divisor of ``batch`` whose (pixel, surface) pairs stay within
    ``BATCH_ELEMENTS`` (read when called; a divisor, so that ``lax.map`` compiles one chunk and no
    remainder)."""
    most = max(1, BATCH_ELEMENTS // max(1, height * width * R.surfaces()))
    return max(k for k in range(1, min(most, batch) + 1) if batch % k == 0)


def render_batched(R, camera, geoms, tau, gamma, target=None):
    """``image.render_jax``, the same function under every transformation, drawn by the C++ kernel
    where there is one (``target``, its FFI target; None: JAX), else by a ``jax.vmap`` of the
    JAX version in chunks of ``batch_chunk`` cameras (``lax.map``) rather than as one array
    program. Its JVP (``custom_jvp``) is ``render_jax``'s, whose reverse mode is the kernel's
    reverse pass (``linear.jvp_with_pullback``: a custom VJP alone would leave ``jax.jacfwd``,
    visual Real2Sim's Jacobians, nothing to go through)."""

    static = isinstance(tau, (int, float)) and isinstance(gamma, (int, float))
    # NumPy leaves (a vmap's batched ones too, which stay NumPy inside the batch tracer) made
    # arrays: custom_jvp takes only canonical arrays
    camera, geoms = jax.tree_util.tree_map(lambda x: jnp.asarray(x) * 1, (camera, geoms))
    dt = jnp.result_type(camera.pos.dtype, geoms.xpos.dtype)
    # the temperatures travel as an argument (the kernel's input), so that a traced tau (an
    # annealed fit's) is drawn by the kernel too; a Python tau stays static for JAX (0: hard)
    tg = jnp.stack([jnp.asarray(tau, dt), jnp.asarray(gamma, dt)])

    def plain(c, g, tg):
        return render_jax(R, c, g, tau if static else tg[0], gamma if static else tg[1])

    def primal(c, g, tg):
        return plain(c, g, tg) if target is None else render_native(R, c, g, tg, target)

    @jax.custom_batching.custom_vmap
    def chunked(c, g, tg):
        return primal(c, g, tg)

    @chunked.def_vmap
    def _rule(axis_size, in_batched, c, g, tg):
        leaves, tree = jax.tree_util.tree_flatten((c, g, tg))
        flags = tree.flatten_up_to(tuple(in_batched))
        batched = [x for x, b in zip(leaves, flags) if b]

        def one(xs):
            it = iter(xs)
            return primal(*jax.tree_util.tree_unflatten(
                tree, [next(it) if b else x for x, b in zip(leaves, flags)]))

        # the C++ kernel takes the whole batch (its rows split across the cores)
        k = axis_size if target is not None else batch_chunk(R, c.height, c.width, axis_size)
        out = (jax.vmap(one)(batched) if k >= axis_size
               else jax.lax.map(one, batched, batch_size=k))
        return out, jax.tree_util.tree_map(lambda _: True, out)

    @jax.custom_jvp
    def render(c, g, tg):
        return chunked(c, g, tg)

    def through_jax(cgt, ct):
        return jax.vjp(plain, *cgt)[1](ct)

    @jax.custom_jvp
    def pullback(cgt, ct):
        c, g, tg = cgt
        return (*pullback_native(R, c, g, tg, ct, target), jnp.zeros_like(tg))

    @pullback.defjvp
    def _pullback_jvp(primals, tangents):  # second derivatives: through JAX
        return jax.jvp(through_jax, primals, tangents)

    def _jvp(primals, tangents):
        through_kernel = target is not None and isinstance(tangents[2], SymbolicZero)
        tangents = jax.tree_util.tree_map(_instantiate, tangents,
                                          is_leaf=lambda x: isinstance(x, SymbolicZero))
        if not through_kernel:  # (or a derivative w.r.t. the temperatures: JAX has one)
            return jax.jvp(plain, primals, tangents)
        # the kernel draws the image; forward mode differentiates the JAX renderer, reverse
        # mode runs the kernel's reverse pass (``linear.jvp_with_pullback``)
        t = linear.jvp_with_pullback(lambda cgt: plain(*cgt), pullback, primals, tangents)
        return render(*primals), t  # (itself: differentiable again, e.g. a Hessian)

    render.defjvp(_jvp, symbolic_zeros=True)
    return render(camera, geoms, tg)


def _instantiate(t):
    """A symbolic zero tangent as an array (``float0`` for integer primals)."""
    if not isinstance(t, SymbolicZero):
        return t
    if t.dtype == jax.dtypes.float0:
        return np.zeros(t.shape, jax.dtypes.float0)
    return jnp.zeros(t.shape, t.dtype)


render_jit = jax.jit(render_batched, static_argnums=(0, 3, 4, 5))
"""``render_batched`` compiled, the renderer, ``tau``, ``gamma`` and the kernel's target static:
``Renderer.render`` called outside ``jit`` with Python-number temperatures."""
