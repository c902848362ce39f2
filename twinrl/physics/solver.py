"""Constraint solve with a fixed iteration count, so reverse-mode AD works through contacts.

Stock MJX (``mujoco.mjx._src.solver.solve``, pinned mujoco-mjx 3.17.0) runs its outer
Newton/CG loop in ``jax.lax.while_loop``; ``jax.grad`` of anything downstream of an active
constraint then fails with "Reverse-mode differentiation does not work for lax.while_loop"
(upstream mujoco issue #2259). With ``gradient="unrolled"`` the same loop body runs inside
``lax.scan`` for exactly ``m.opt.iterations`` steps and turns into a no-op once the stock
convergence test says done, so the forward result is the stock result bit for bit (tested in
``tests/physics/test_solver.py``) and the reverse pass exists. With ``gradient="implicit"`` (the
default) the iterations are never differentiated, so the forward keeps the stock ``while_loop``
(``converge``): under ``vmap`` a scan's no-op ``cond`` becomes a ``select`` that computes every
iteration, and a user's MJCF with MuJoCo's default 100 iterations paid all 100 every step (a
float64 gradcheck of a 2-link arm on a box, in the suite: 368 s -> 41 s).

Backward NaN. Once a solve has converged, the search direction is ~0 and the line search
divides by its own curvature ``deriv_1`` (a ~0 number, floored at mjMINVAL): the body's
partial derivatives are then huge or infinite. The no-op branch of ``lax.cond`` discards that
value, but where ``cond`` is lowered to ``select`` (under ``vmap``) the cotangent of the
untaken branch is 0, and 0 * inf = NaN. We therefore feed the body a *safe* context when the
solve is done (the "double where" trick): the discarded computation then stays finite.

Which derivative. Differentiating the unrolled iterations gives the derivative of the
*iterations*, not of the solution they converge to: its line search stops on a tolerance and its
bracketing switches pieces of a piecewise quadratic, so the iterates' derivative can be off by
orders of magnitude where the solution's is small. Measured on a free box landing flat on a plane
(4 corner contacts, float64): one step's Jacobian 2,991 by unrolled reverse mode against 25.7 by
central differences, a rollout gradient 10^6 too large. ``gradient="implicit"`` (the default)
therefore differentiates the *converged* solution by the implicit function theorem (as
differentiable convex-optimisation layers do, e.g. Amos & Kolter, OptNet, ICML 2017; Agrawal et
al., NeurIPS 2019): MuJoCo's constraint solve minimises the convex cost

    c(a) = 1/2 (a - a_smooth)' M (a - a_smooth) + s(J a - a_ref)

over accelerations ``a`` (Todorov, "Convex and analytically-invertible dynamics with contacts
and constraints", ICRA 2014), so its minimiser satisfies ``r(a, theta) = M a - qfrc_smooth -
J' f(J a - a_ref) = 0`` and ``da/dtheta = -H^-1 dr/dtheta`` with ``H = dr/da`` (M plus the
active rows' curvature: positive definite). ``jax.lax.custom_root`` does exactly this: the
forward value is the fixed-iteration solve below (so it stays stock MJX's), the derivative is
one nv x nv linear solve per step. ``gradient="unrolled"`` keeps differentiating the iterations.

We reuse the stock building blocks (``Context``, ``_linesearch``, ``_update_constraint``,
``_update_gradient``) of the pinned version rather than copying them, and replace only the loop.
``forward`` mirrors ``mujoco.mjx._src.forward.forward`` with this solve swapped in, and with
``twinrl.physics.smooth``'s kinematics and tree sums in place of stock's (equal to rounding,
10x fewer jaxpr equations: an arm task's episode gradient traces and compiles 2.5x faster); time
stepping is in ``twinrl.physics.integrator``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
from mujoco.mjx._src import forward as _fwd
from mujoco.mjx._src import math as _math
from mujoco.mjx._src import sensor as _sensor
from mujoco.mjx._src import solver as _stock
from mujoco.mjx._src.types import DisableBit, SolverType

from twinrl.physics import collision as _collision
from twinrl.physics import smooth as _tree

__all__ = ["solve", "forward", "converge", "GRADIENTS"]

# How reverse mode goes through the constraint solve (module docstring).
GRADIENTS = ("implicit", "unrolled")


def _done(m, d, ctx) -> jax.Array:
    """The stock convergence test (``solve.cond`` negated), without the iteration cap, and done
    once the cost or its gradient is not finite. Stock's test compares NaN with the tolerance,
    never true, so a solve gone NaN (a mass matrix made indefinite: armature stepped below 0 on
    a light body) ran every iteration, each with every line-search iteration, and under ``vmap``
    held its whole batch for as long: 40x a finite rollout (the Control Suite's stacker, 20
    steps). Iterating from NaN gives NaN, so a finite result is stock's, bit for bit. (Not the
    improvement's finiteness: the first iteration's previous cost is infinite.)"""
    improvement = _stock._rescale(m, d, ctx.prev_cost - ctx.cost)
    gradient = _stock._rescale(m, d, _math.norm(ctx.grad))
    return ((improvement < m.opt.tolerance) | (gradient < m.opt.tolerance)
            | ~jnp.isfinite(ctx.cost) | ~jnp.isfinite(gradient))


def _iterate(m, d, ctx):
    """One stock solver iteration: line search, constraint update, new search direction."""
    ctx = _stock._linesearch(m, d, ctx)
    prev_grad, prev_mgrad = ctx.grad, ctx.Mgrad
    ctx = _stock._update_constraint(m, d, ctx)
    ctx = _stock._update_gradient(m, d, ctx)
    if m.opt.solver == SolverType.NEWTON:
        search = -ctx.Mgrad
    else:  # Polak-Ribiere conjugate gradient, as in the stock solver
        beta = jnp.dot(ctx.grad, ctx.Mgrad - prev_mgrad)
        beta = beta / jnp.maximum(mujoco.mjMINVAL, jnp.dot(prev_grad, prev_mgrad))
        search = -ctx.Mgrad + jnp.maximum(0, beta) * ctx.search
    return ctx.replace(search=search, solver_niter=ctx.solver_niter + 1)


def _safe(ctx):
    """A context on which one more iteration is finite with finite derivatives.

    Only the search direction matters: a unit direction gives the line search a curvature
    bounded away from zero. The result of that iteration is always discarded.
    """
    search = jnp.zeros_like(ctx.search).at[..., 0].set(1.0) if ctx.search.size else ctx.search
    return ctx.replace(search=search)


def _iterations(m, d, ctx, n_iter: int):
    """``n_iter`` stock iterations from ``ctx``, no-ops once converged (reverse-AD-able)."""
    if n_iter == 1:  # the stock solver runs the body once, unconditionally
        return _iterate(m, d, ctx)

    def body(ctx, _):
        done = _done(m, d, ctx)
        # Double where: the discarded branch must see finite inputs (module docstring).
        ctx_in = jax.tree_util.tree_map(
            lambda safe, x: jnp.where(done, safe, x), _safe(ctx), ctx)
        new = jax.lax.cond(done, lambda c: c, lambda c: _iterate(m, d, c), ctx_in)
        ctx = jax.tree_util.tree_map(lambda old, nw: jnp.where(done, old, nw), ctx, new)
        return ctx, None

    ctx, _ = jax.lax.scan(body, ctx, None, length=n_iter)
    return ctx


def converge(m, d, ctx, n_iter: int):
    """At most ``n_iter`` stock iterations from ``ctx``, stopping at convergence: the stock
    ``while_loop`` (not reverse-differentiable). The implicit derivative never differentiates the
    iterations, so its forward runs this; under ``vmap`` it stops once every lane has converged,
    where ``_iterations`` computes all ``n_iter`` (its ``cond`` becomes a ``select``): MuJoCo's
    default of 100 iterations cost 100 iterations a step in every batched rollout."""
    if n_iter == 1:  # the stock solver runs the body once, unconditionally
        return _iterate(m, d, ctx)
    return jax.lax.while_loop(lambda c: (c.solver_niter < n_iter) & ~_done(m, d, c),
                              lambda c: _iterate(m, d, c), ctx)


def _residual(m, d, qacc):
    """Gradient of the solve's convex cost at ``qacc``: zero at the solution."""
    ctx = _stock.Context.create(m, d.replace(qacc=qacc), grad=False)
    return ctx.Ma - d.qfrc_smooth - ctx.qfrc_constraint


def _tangent_solve(g, y):
    """Solve ``g(x) = y`` for the linearised residual ``g`` (nv x nv: materialised)."""
    return jnp.linalg.solve(jax.jacfwd(g)(y), y)


def solve(m, d, iterations: int | None = None, gradient: str = "implicit"):
    """Constraint solve equal to stock MJX's, differentiable in reverse mode.

    Args:
      m: ``mjx.Model`` (JAX implementation).
      d: ``mjx.Data`` after ``fwd_acceleration`` (``qacc_smooth`` set).
      iterations: fixed outer iteration count; defaults to ``m.opt.iterations``.
      gradient: ``"implicit"`` (derivative of the converged solution) or ``"unrolled"``
        (derivative of the iterations); module docstring.

    Returns:
      ``d`` with ``qacc``, ``qfrc_constraint`` and ``efc_force`` set.
    """
    n_iter = int(m.opt.iterations if iterations is None else iterations)
    if n_iter < 1:
        raise ValueError(f"solver iterations must be >= 1, got {n_iter}")
    if gradient not in GRADIENTS:
        raise ValueError(f"gradient must be one of {GRADIENTS}, got {gradient!r}")

    qacc = d.qacc_smooth
    if not m.opt.disableflags & DisableBit.WARMSTART:
        warm = _stock.Context.create(m, d.replace(qacc=d.qacc_warmstart), grad=False)
        smth = _stock.Context.create(m, d.replace(qacc=d.qacc_smooth), grad=False)
        qacc = jnp.where(warm.cost < smth.cost, d.qacc_warmstart, d.qacc_smooth)
    d = d.replace(qacc=qacc)

    if gradient == "unrolled":
        ctx = _iterations(m, d, _stock.Context.create(m, d), n_iter)
    else:
        def run(_, qacc0):
            ms, ds = jax.lax.stop_gradient((m, d.replace(qacc=qacc0)))
            return converge(ms, ds, _stock.Context.create(ms, ds), n_iter).qacc

        qacc = jax.lax.custom_root(lambda a: _residual(m, d, a), d.qacc, run, _tangent_solve)
        # forces from the solution, so they carry its derivative too
        ctx = _stock.Context.create(m, d.replace(qacc=qacc), grad=False)

    return d.tree_replace({
        "qfrc_constraint": ctx.qfrc_constraint,
        "qacc": ctx.qacc,
        "_impl.efc_force": ctx.efc_force,
    })


def forward(m, d, iterations: int | None = None, gradient: str = "implicit",
            contacts: str = "mjx"):
    """``mjx.forward`` with the differentiable solve (and differentiable SDF contacts,
    ``twinrl.physics.collision``; ``contacts``: its rule set, ``collision.CONTACTS``)."""
    d = _collision.fwd_position(m, d, contacts)
    d = _sensor.sensor_pos(m, d)
    d = _tree.fwd_velocity(m, d)
    d = _sensor.sensor_vel(m, d)
    d = _fwd.fwd_actuation(m, d)
    d = _fwd.fwd_acceleration(m, d)
    if d._impl.efc_J.size == 0:
        return d.replace(qacc=d.qacc_smooth)
    d = solve(m, d, iterations, gradient)
    return _sensor.sensor_acc(m, d)
