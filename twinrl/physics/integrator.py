"""Time integration for ``Sim``: ``mjx.step`` with our solve and a gradient-correct rotation update.

Two things differ from stock MJX (``mujoco.mjx._src.forward``, pinned mujoco-mjx 3.17.0):

1. every stage calls ``twinrl.physics.solver.forward`` (fixed-iteration, reverse-differentiable
   constraint solve) instead of the stock ``while_loop`` solve;
2. free and ball joints integrate their quaternion with ``quat_integrate`` below. The stock one
   normalises the angular velocity through ``math.norm``, which replaces any vector within 1e-8
   of zero by ones to keep the norm's gradient finite -- and so gives an *exactly zero* gradient
   of the new orientation with respect to the angular velocity of a body at rest. A box resting
   on a table then has no gradient through its spin, and a gradient check of the push scene
   failed by a factor of 4 (measured: AD 0 vs finite differences dt/2 per step). Here the
   rotation ``exp(w dt / 2)`` is written with ``sin(n)/n`` replaced by its Taylor series near 0,
   which is exact to rounding and has the right derivative (identity) at ``w = 0``.

Forward results equal stock ``mjx.step`` to rounding (tests compare trajectories of every bundled
scene; the stock map drops rotations below 1e-8 rad/s, ours keeps them).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from mujoco.mjx._src import forward as _fwd
from mujoco.mjx._src import math as _math
from mujoco.mjx._src import scan as _scan
from mujoco.mjx._src import smooth as _smooth
from mujoco.mjx._src import support as _support
from mujoco.mjx._src import derivative as _derivative
from mujoco.mjx._src.types import DisableBit, IntegratorType, JointType

from twinrl.physics.solver import forward

__all__ = ["step", "quat_integrate", "tangent_qpos", "tangent_delta"]

# Below this |w dt / 2|^2, sin(n)/n and cos(n) use their Taylor series (error < 1e-20).
_SMALL = 1e-8


def quat_integrate(q: jax.Array, w: jax.Array, dt) -> jax.Array:
    """Rotate unit quaternion ``q`` by body angular velocity ``w`` over ``dt``; smooth at w = 0."""
    half = 0.5 * dt * w
    n2 = jnp.sum(half * half)
    small = n2 < _SMALL
    n = jnp.sqrt(jnp.where(small, 1.0, n2))  # double where: no sqrt'(0) in the unused branch
    sinc = jnp.where(small, 1.0 - n2 / 6.0, jnp.sin(n) / n)
    cos = jnp.where(small, 1.0 - n2 / 2.0, jnp.cos(n))
    dq = jnp.concatenate([cos[None], sinc * half])
    return _math.normalize(_math.quat_mul(q, dq))


def tangent_qpos(jnt_types, qpos0: jax.Array, dq: jax.Array) -> jax.Array:
    """``qpos0 (+) dq``: ``dq`` (nv,) moves slides/hinges/translations additively and rotates
    each quaternion by the body-frame rotation vector ``dq`` (``q0 * exp(dq / 2)``). The
    coordinates in which a state is perturbed (``twinrl.physics.gradcheck``) or estimated
    (sysid's window starts): no direction that changes only a quaternion's norm."""
    out, qi, vi = [], 0, 0
    for jt in jnt_types:
        if jt == JointType.FREE:
            out += [qpos0[qi:qi + 3] + dq[vi:vi + 3],
                    quat_integrate(qpos0[qi + 3:qi + 7], dq[vi + 3:vi + 6], 1.0)]
            qi, vi = qi + 7, vi + 6
        elif jt == JointType.BALL:
            out.append(quat_integrate(qpos0[qi:qi + 4], dq[vi:vi + 3], 1.0))
            qi, vi = qi + 4, vi + 3
        else:
            out.append(qpos0[qi:qi + 1] + dq[vi:vi + 1])
            qi, vi = qi + 1, vi + 1
    return jnp.concatenate(out) if out else qpos0


def _rotation_vector(q0: jax.Array, q1: jax.Array) -> jax.Array:
    """The body-frame rotation vector ``w`` with ``q1 = q0 * exp(w / 2)`` (the shorter way)."""
    r = _math.quat_mul(_math.quat_inv(q0), q1)
    r = jnp.where(r[0] < 0, -r, r) / jnp.linalg.norm(r)
    s2 = jnp.sum(r[1:] * r[1:])
    small = s2 < 1e-16
    s = jnp.sqrt(jnp.where(small, 1.0, s2))
    # angle / sin(angle / 2), with its Taylor series near 0 (finite derivative at the identity)
    scale = jnp.where(small, 2.0 + s2 / 3.0, 2.0 * jnp.arctan2(s, r[0]) / s)
    return scale * r[1:]


def tangent_delta(jnt_types, qpos0: jax.Array, qpos1: jax.Array) -> jax.Array:
    """The inverse of ``tangent_qpos``: ``dq`` (nv,) with ``qpos1 = qpos0 (+) dq`` (rotations
    below half a turn)."""
    out, qi = [], 0
    for jt in jnt_types:
        if jt == JointType.FREE:
            out += [qpos1[qi:qi + 3] - qpos0[qi:qi + 3],
                    _rotation_vector(qpos0[qi + 3:qi + 7], qpos1[qi + 3:qi + 7])]
            qi += 7
        elif jt == JointType.BALL:
            out.append(_rotation_vector(qpos0[qi:qi + 4], qpos1[qi:qi + 4]))
            qi += 4
        else:
            out.append(qpos1[qi:qi + 1] - qpos0[qi:qi + 1])
            qi += 1
    return jnp.concatenate(out) if out else qpos1 - qpos0


def _integrate_pos(jnt_types, qpos, qvel, dt):
    out, qi, vi = [], 0, 0
    for jt in jnt_types:
        if jt == JointType.FREE:
            out += [qpos[qi:qi + 3] + dt * qvel[vi:vi + 3],
                    quat_integrate(qpos[qi + 3:qi + 7], qvel[vi + 3:vi + 6], dt)]
            qi, vi = qi + 7, vi + 6
        elif jt == JointType.BALL:
            out.append(quat_integrate(qpos[qi:qi + 4], qvel[vi:vi + 3], dt))
            qi, vi = qi + 4, vi + 3
        elif jt in (JointType.HINGE, JointType.SLIDE):
            out.append((qpos[qi] + dt * qvel[vi])[None])
            qi, vi = qi + 1, vi + 1
        else:
            raise RuntimeError(f"unrecognized joint type: {jt}")
    return jnp.concatenate(out) if out else jnp.empty((0,))


def _advance(m, d, act_dot, qacc, qvel=None):
    """Stock ``_advance`` (semi-implicit Euler on positions) with our ``_integrate_pos``."""
    act = _fwd._next_activation(m, d, act_dot)
    d = d.replace(qvel=d.qvel + qacc * m.opt.timestep)
    qvel = d.qvel if qvel is None else qvel
    integrate = lambda *args: _integrate_pos(*args, dt=m.opt.timestep)
    qpos = _scan.flat(m, integrate, "jqv", "q", m.jnt_type, d.qpos, qvel)
    d = d.replace(qacc_warmstart=d.qacc)
    return d.replace(act=act, qpos=qpos, time=d.time + m.opt.timestep)


def _euler(m, d):
    qacc = d.qacc
    if not m.opt.disableflags & DisableBit.EULERDAMP:  # damping integrated implicitly
        if _support.is_sparse(m):
            diag = m.M_rowadr + m.M_rownnz - 1
            mass = d._impl.M.at[diag].add(m.opt.timestep * m.dof_damping)
        else:
            mass = d._impl.M + jnp.diag(m.opt.timestep * m.dof_damping)
        dh = _smooth.factor_m(m, d.tree_replace({"_impl.M": mass}))
        qacc = _smooth.solve_m(m, dh, d.qfrc_smooth + d.qfrc_constraint)
    return _advance(m, d, d.act_dot, qacc)


def _implicit(m, d):
    qderiv = _derivative.deriv_smooth_vel(m, d)
    qacc = d.qacc
    if qderiv is not None:
        qm = _support.full_m(m, d) if _support.is_sparse(m) else d._impl.M
        qh, _ = jax.scipy.linalg.cho_factor(qm - m.opt.timestep * qderiv)
        qacc = jax.scipy.linalg.cho_solve((qh, False), d.qfrc_smooth + d.qfrc_constraint)
    return _advance(m, d, d.act_dot, qacc)


def _rk4(m, d, iterations, gradient, contacts):
    a, b = _fwd._RK4_A, _fwd._RK4_B
    times = d.time + jnp.tril(a).sum(axis=0) * m.opt.timestep
    d0 = d
    qvel, qacc, act_dot = b[0] * d.qvel, b[0] * d.qacc, b[0] * d.act_dot
    kqvel = d.qvel
    integrate = lambda *args: _integrate_pos(*args, dt=m.opt.timestep)
    for i in range(3):
        kqpos = _scan.flat(m, integrate, "jqv", "q", m.jnt_type, d0.qpos, a[i, i] * kqvel)
        kact = d0.act + a[i, i] * d.act_dot * m.opt.timestep
        kqvel = d0.qvel + a[i, i] * d.qacc * m.opt.timestep
        d = forward(m, d.replace(qpos=kqpos, qvel=kqvel, act=kact, time=times[i]), iterations,
                    gradient, contacts)
        qvel += b[i + 1] * kqvel
        qacc += b[i + 1] * d.qacc
        act_dot += b[i + 1] * d.act_dot
    d = d.replace(qpos=d0.qpos, qvel=d0.qvel, act=d0.act, time=d0.time)
    return _advance(m, d, act_dot, qacc, qvel)


def step(m, d, iterations: int | None = None, gradient: str = "implicit",
         contacts: str = "mjx"):
    """``mjx.step`` with the differentiable solve (Euler, implicitfast or RK4 integrator).

    ``gradient``: how reverse mode goes through the constraint solve (``twinrl.physics.solver``);
    ``contacts``: the collision rule set (``twinrl.physics.collision.CONTACTS``).
    """
    d0 = d
    d = forward(m, d, iterations, gradient, contacts)
    if m.opt.integrator == IntegratorType.EULER:
        d = _euler(m, d)
    elif m.opt.integrator == IntegratorType.IMPLICITFAST:
        d = _implicit(m, d)
    elif m.opt.integrator == IntegratorType.RK4:
        d = _rk4(m, d, iterations, gradient, contacts)
    else:
        raise NotImplementedError(f"integrator {m.opt.integrator} is not supported by MJX")
    return same_dtypes(d, d0)


def same_dtypes(new, old):
    """``new`` with every leaf cast to the dtype of ``old``'s leaf. MJX 3.17's tendon wrapping
    writes ``ten_wrapadr``, ``ten_wrapnum`` and ``wrap_obj`` as int64 under x64 where
    ``make_data`` made them int32, so a ``lax.scan`` over stock ``mjx.step`` fails on any model
    with a tendon in float64; a step that returns what it was given scans."""
    return jax.tree_util.tree_map(
        lambda a, b: a if a.dtype == b.dtype else a.astype(b.dtype), new, old)
