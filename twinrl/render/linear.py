"""A function's derivative whose forward mode and reverse mode are computed differently.

``jax.custom_jvp`` gives a function one derivative rule, and reverse mode transposes it: the
render's JVP through the JAX renderer, transposed by XLA, was the cost of every gradient of an
image. ``jvp_with_pullback(fun, pullback, primals, tangents)`` is a JVP rule's tangent whose
forward evaluation is ``jax.jvp(fun, ...)`` (``jax.jvp``, ``jax.jacfwd``, ``jax.linearize``:
JAX, as before) and whose transpose (``jax.grad``, ``jax.vjp``, ``jax.jacrev``) is
``pullback(primals, cotangents)``: the C++ renderer's reverse kernel. It is one primitive
(``jax.extend``), linear in the tangents, with the JAX extension points every primitive has:
evaluation and lowering through ``fun``'s JVP, a batching rule (vmap over tangents is
``jax.jacfwd``), a JVP (second derivatives through ``fun``) and the transpose.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

__all__ = ["jvp_with_pullback"]

_lin_p = Primitive("twinrl_linear")
_lin_p.multiple_results = True


def _inexact(x) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


def _float0(shape):
    return np.zeros(shape, jax.dtypes.float0)


class _Spec:
    """What the primitive's parameters carry (hashable by identity): ``fun`` and ``pullback``,
    the primals' tree and which of its leaves are differentiable, and the outputs' tree, avals
    and which of them are."""

    def __init__(self, fun, pullback, tree, diff, out_tree, out_avals, out_diff):
        self.fun, self.pullback = fun, pullback
        self.tree, self.diff = tree, diff
        self.out_tree, self.out_avals, self.out_diff = out_tree, out_avals, out_diff

    def primals(self, leaves):
        return jax.tree_util.tree_unflatten(self.tree, leaves)

    def tangents(self, leaves, dleaves):
        it = iter(dleaves)
        return jax.tree_util.tree_unflatten(
            self.tree, [next(it) if d else _float0(np.shape(x))
                        for x, d in zip(leaves, self.diff)])

    def jvp(self, *args):
        """Tangents of the differentiable outputs (a list) at primal leaves, along tangent
        leaves of the differentiable inputs (``args``: the two, concatenated)."""
        n = len(self.diff)
        leaves, dleaves = args[:n], args[n:]
        _, t = jax.jvp(self.fun, (self.primals(leaves),), (self.tangents(leaves, dleaves),))
        return [x for x, d in zip(jax.tree_util.tree_leaves(t), self.out_diff) if d]

    def vjp(self, leaves, cts):
        """Cotangents of the differentiable inputs (a list) from those of the differentiable
        outputs."""
        it = iter(cts)
        ct = jax.tree_util.tree_unflatten(
            self.out_tree, [next(it) if d else _float0(a.shape)
                            for a, d in zip(self.out_avals, self.out_diff)])
        g = self.pullback(self.primals(leaves), ct)
        gl = self.tree.flatten_up_to(g)
        return [x for x, d in zip(gl, self.diff) if d]


def jvp_with_pullback(fun, pullback, primals, tangents):
    """The tangent of ``fun(primals)`` along ``tangents`` (``fun`` takes one pytree), for a
    ``jax.custom_jvp`` rule: forward mode runs ``jax.jvp(fun, ...)``; reverse mode runs
    ``pullback(primals, cotangent)`` (a pytree like ``primals``; ``cotangent`` like ``fun``'s
    output, with ``float0`` zeros where that is not a float) instead of transposing it."""
    leaves, tree = jax.tree_util.tree_flatten(primals)
    diff = tuple(_inexact(x) for x in leaves)
    tl = tree.flatten_up_to(tangents)
    out = jax.eval_shape(fun, primals)
    out_leaves, out_tree = jax.tree_util.tree_flatten(out)
    out_avals = tuple(jax.core.ShapedArray(o.shape, o.dtype) for o in out_leaves)
    out_diff = tuple(_inexact(o) for o in out_leaves)
    spec = _Spec(fun, pullback, tree, diff, out_tree, out_avals, out_diff)
    dleaves = [jnp.asarray(ad.instantiate_zeros(t), x.dtype)
               for t, x, d in zip(tl, leaves, diff) if d]
    res = _lin_p.bind(*leaves, *dleaves, spec=spec)
    it = iter(res)
    return jax.tree_util.tree_unflatten(
        out_tree, [next(it) if d else _float0(a.shape)
                   for a, d in zip(out_avals, out_diff)])


def _abstract(*args, spec):
    return [a for a, d in zip(spec.out_avals, spec.out_diff) if d]


def _impl(*args, spec):
    return spec.jvp(*args)


def _transpose(cts, *args, spec):
    n = len(spec.diff)
    leaves, dleaves = args[:n], args[n:]
    if any(ad.is_undefined_primal(x) for x in leaves):
        raise NotImplementedError("twinrl_linear is linear in its tangents only")
    grads = spec.vjp(leaves, [ad.instantiate_zeros(c) for c in cts])
    return [None] * n + [g if ad.is_undefined_primal(t) else None
                         for g, t in zip(grads, dleaves)]


def _batch(args, dims, *, spec):
    axes = [None if d is batching.not_mapped else d for d in dims]
    out = jax.vmap(lambda *a: spec.jvp(*a), in_axes=axes)(*args)
    return out, [0] * len(out)


def _jvp(primals, tangents, *, spec):
    # second derivatives (a Hessian, a JVP of a gradient) go through ``fun`` in JAX
    tangents = [ad.instantiate_zeros(t) for t in tangents]
    return jax.jvp(lambda *a: spec.jvp(*a), primals, tangents)


_lin_p.def_impl(_impl)
_lin_p.def_abstract_eval(_abstract)
mlir.register_lowering(_lin_p, mlir.lower_fun(_impl, multiple_results=True))
ad.primitive_transposes[_lin_p] = _transpose
ad.primitive_jvps[_lin_p] = _jvp
batching.primitive_batchers[_lin_p] = _batch
