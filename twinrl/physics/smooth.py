"""The ``mjx`` stages that walk the body tree, in a tenth of the jaxpr equations: kinematics
(body, joint, geom and site frames), ``com_pos``, ``crb``, ``com_vel``, ``rne``, ``fwd_velocity``.

Stock ``mjx`` (pinned mujoco-mjx 3.17.0) walks the tree with ``scan.body_tree``: for every depth
it gathers the inputs of that depth's bodies, ``vmap``s a per-body function written with scalar
indexing (``quat_mul`` is 16 indexing ops and 24 arithmetic ones) and scatters the results back.
For a serial chain every depth holds one body, so a Panda task's kinematics (12 bodies) was
7,669 jaxpr equations -- 43 % of a whole physics step -- and its reverse-mode trace alone took
5 s on 2 cores, paid again by every new function that differentiates an arm step (the persistent
compilation cache saves compiles, never traces).

Here kinematics follows the same rules (``mj_kinematics``: a body's frame from its parent's and
its ``body_pos``/``body_quat``, then its joints in order -- a free joint sets the frame from
``qpos``, a ball or a hinge rotates the frame about the joint's anchor, a slide moves it along
the joint's axis, all by ``qpos - qpos0``; free and ball quaternions are normalised in ``qpos``)
as one Python loop over the bodies, with quaternion products and rotations as contractions with
constant tensors (two or three equations each) and every hinge's local rotation computed at
once. The other stages sum along the tree (a body's ancestors, or its subtree) with one
contraction by the tree's constant 0/1 ancestor matrix, around stock's own per-body algebra.
The tree structure (parents, joint types, addresses) is static NumPy on the ``mjx.Model``; every
frame, axis and inertia is read from the model it is given, so identified parameters reach it.

Each stage equals stock's on every field it writes, forward and gradient
(``tests/physics/test_smooth.py``, float64: a model with every joint type, nesting, rotated
frames, off-centre anchors, mocap bodies and sites, and the Panda); ``bench/trace.py`` (in git history) measures
the equations and trace times of both and an arm episode gradient's lower/compile/run with each.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco.mjx._src import math as _math
from mujoco.mjx._src import passive as _passive
from mujoco.mjx._src import smooth as _smooth
from mujoco.mjx._src import support as _support
from mujoco.mjx._src.types import DisableBit, JointType

_MINVAL = float(mujoco.mjMINVAL)

__all__ = ["kinematics", "com_pos", "crb", "com_vel", "rne", "passive", "fwd_velocity", "quat_mul",
           "quat_to_mat"]

# quat_mul(u, v)_j = sum_ik u_i _QMUL[i, j, k] v_k  (Hamilton product, w first)
_QMUL = np.zeros((4, 4, 4))
for _i, _j, _k, _s in [(0, 0, 0, 1), (1, 0, 1, -1), (2, 0, 2, -1), (3, 0, 3, -1),
                       (0, 1, 1, 1), (1, 1, 0, 1), (2, 1, 3, 1), (3, 1, 2, -1),
                       (0, 2, 2, 1), (1, 2, 3, -1), (2, 2, 0, 1), (3, 2, 1, 1),
                       (0, 3, 3, 1), (1, 3, 2, 1), (2, 3, 1, -1), (3, 3, 0, 1)]:
    _QMUL[_i, _j, _k] = _s

# quat_to_mat(q)_rc = sum_kl q_k q_l _QMAT[k, l, r, c]  (the rotation of a unit quaternion)
_QMAT = np.zeros((4, 4, 3, 3))
for _r, _c, _terms in [
        (0, 0, [(0, 0, 1), (1, 1, 1), (2, 2, -1), (3, 3, -1)]),
        (0, 1, [(1, 2, 2), (0, 3, -2)]), (0, 2, [(1, 3, 2), (0, 2, 2)]),
        (1, 0, [(1, 2, 2), (0, 3, 2)]),
        (1, 1, [(0, 0, 1), (1, 1, -1), (2, 2, 1), (3, 3, -1)]),
        (1, 2, [(2, 3, 2), (0, 1, -2)]), (2, 0, [(1, 3, 2), (0, 2, -2)]),
        (2, 1, [(2, 3, 2), (0, 1, 2)]),
        (2, 2, [(0, 0, 1), (1, 1, -1), (2, 2, -1), (3, 3, 1)])]:
    for _k, _l, _s in _terms:
        _QMAT[_k, _l, _r, _c] = _s


def quat_mul(u: jax.Array, v: jax.Array) -> jax.Array:
    """Hamilton product ``u * v`` of quaternions (w, x, y, z), as two contractions."""
    return jnp.einsum("i,ijk,k->j", u, jnp.asarray(_QMUL, u.dtype), v)


def quat_to_mat(q: jax.Array) -> jax.Array:
    """Rotation matrix (3, 3) of a unit quaternion, as two contractions."""
    return jnp.einsum("k,l,klrc->rc", q, q, jnp.asarray(_QMAT, q.dtype))


def _local_rotations(m, qpos):
    """Every hinge joint's local quaternion ``(njnt, 4)`` (identity rows for the others)."""
    types = np.asarray(m.jnt_type)
    rows = np.flatnonzero(types == JointType.HINGE)
    out = jnp.zeros((types.size, 4), qpos.dtype).at[:, 0].set(1.0)
    if rows.size == 0:
        return out
    adr = np.asarray(m.jnt_qposadr)[rows]
    angle = qpos[adr] - jnp.asarray(m.qpos0, qpos.dtype)[adr]
    axis = jnp.asarray(m.jnt_axis, qpos.dtype)[rows]
    return out.at[rows].set(jax.vmap(_math.axis_angle_to_quat)(axis, angle))


def kinematics(m, d):
    """``mujoco.mjx.kinematics(m, d)``: the same fields, equal to rounding (module docstring)."""
    dt = d.qpos.dtype
    types = np.asarray(m.jnt_type)
    qadr = np.asarray(m.jnt_qposadr)
    parent = np.asarray(m.body_parentid)
    jadr, jnum = np.asarray(m.body_jntadr), np.asarray(m.body_jntnum)
    qpos = d.qpos
    qloc = _local_rotations(m, qpos)
    body_pos = jnp.asarray(m.body_pos, dt)
    body_quat = jnp.asarray(m.body_quat, dt)
    jnt_pos = jnp.asarray(m.jnt_pos, dt)
    jnt_axis = jnp.asarray(m.jnt_axis, dt)
    z = jnp.asarray([0.0, 0.0, 1.0], dt)

    xpos, xquat, xmat = [body_pos[0]], [body_quat[0]], [quat_to_mat(body_quat[0])]
    anchors, axes = [None] * types.size, [None] * types.size
    for b in range(1, int(m.nbody)):
        p = int(parent[b])
        pos = xpos[p] + xmat[p] @ body_pos[b]
        quat = quat_mul(xquat[p], body_quat[b])
        mat = None  # quat_to_mat(quat), computed when a joint or the body needs it
        for j in range(int(jadr[b]), int(jadr[b]) + int(jnum[b])):
            t, a = int(types[j]), int(qadr[j])
            if t == JointType.FREE:
                anchors[j], axes[j] = qpos[a:a + 3], z
                pos = qpos[a:a + 3]
                quat = _math.normalize(qpos[a + 3:a + 7])
                qpos = qpos.at[a + 3:a + 7].set(quat)
                mat = None
                continue
            mat = quat_to_mat(quat) if mat is None else mat
            anchor = pos + mat @ jnt_pos[j]
            anchors[j], axes[j] = anchor, mat @ jnt_axis[j]
            if t == JointType.SLIDE:
                pos = pos + axes[j] * (qpos[a] - jnp.asarray(m.qpos0, dt)[a])
                continue
            if t == JointType.BALL:
                local = _math.normalize(qpos[a:a + 4])
                qpos = qpos.at[a:a + 4].set(local)
            elif t == JointType.HINGE:
                local = qloc[j]
            else:
                raise RuntimeError(f"unrecognized joint type: {t}")
            quat = quat_mul(quat, local)
            mat = quat_to_mat(quat)
            pos = anchor - mat @ jnt_pos[j]
        xpos.append(pos)
        xquat.append(quat)
        xmat.append(quat_to_mat(quat) if mat is None else mat)
    xpos, xquat, xmat = jnp.stack(xpos), jnp.stack(xquat), jnp.stack(xmat)
    xanchor = jnp.stack(anchors) if anchors else jnp.zeros((0, 3), dt)
    xaxis = jnp.stack(axes) if axes else jnp.zeros((0, 3), dt)

    if m.nmocap:
        mocap = np.asarray(m.body_mocapid) >= 0
        mocap_quat = jax.vmap(_math.normalize)(d.mocap_quat)
        xpos = xpos.at[mocap].set(d.mocap_pos)
        xquat = xquat.at[mocap].set(mocap_quat)
        xmat = xmat.at[mocap].set(jax.vmap(quat_to_mat)(mocap_quat))

    to_global = jax.vmap(_to_global)
    xipos, ximat = to_global(xpos, xquat, m.body_ipos, m.body_iquat)
    d = d.replace(qpos=qpos, xanchor=xanchor, xaxis=xaxis, xpos=xpos)
    d = d.replace(xquat=xquat, xmat=xmat, xipos=xipos, ximat=ximat)
    if m.ngeom:
        g = np.asarray(m.geom_bodyid)
        geom_xpos, geom_xmat = to_global(xpos[g], xquat[g], m.geom_pos, m.geom_quat)
        d = d.replace(geom_xpos=geom_xpos, geom_xmat=geom_xmat)
    if m.nsite:
        s = np.asarray(m.site_bodyid)
        site_xpos, site_xmat = to_global(xpos[s], xquat[s], m.site_pos, m.site_quat)
        d = d.replace(site_xpos=site_xpos, site_xmat=site_xmat)
    return d


def _to_global(pos, quat, local_pos, local_quat):
    dt = pos.dtype
    mat = quat_to_mat(quat)
    return (pos + mat @ jnp.asarray(local_pos, dt),
            quat_to_mat(quat_mul(quat, jnp.asarray(local_quat, dt))))


# ------------------------------------------------------------------ sums along the tree
# Stock ``com_pos``, ``crb``, ``com_vel`` and ``rne`` carry sums down (root to leaves) or up the
# tree with ``scan.body_tree``. A sum over a body's ancestors is a product with the tree's
# constant 0/1 ancestor matrix, one contraction whatever the depth; the per-body algebra between
# the sums is stock's own, ``vmap``ped.


def _ancestors(m) -> np.ndarray:
    """``A[b, c] = 1`` where body ``c`` is body ``b`` or one of its ancestors (world included)."""
    parent = np.asarray(m.body_parentid)
    a = np.zeros((int(m.nbody), int(m.nbody)))
    for b in range(int(m.nbody)):
        c = b
        while True:
            a[b, c] = 1.0
            if c == 0:
                break
            c = int(parent[c])
    return a


def _down(m, x):
    """``y[b] = sum of x[c]`` over ``c`` = ``b`` and its ancestors (``x``: (nbody, ...))."""
    return jnp.tensordot(jnp.asarray(_ancestors(m), x.dtype), x, axes=1)


def _up(m, x):
    """``y[b] = sum of x[c]`` over ``c`` = ``b`` and its descendants (the subtree's sum)."""
    return jnp.tensordot(jnp.asarray(_ancestors(m).T, x.dtype), x, axes=1)


def _dof_to_body(m, x):
    """``(nbody, ...)`` sums of the per-dof rows ``x`` (nv, ...) over each body's dofs."""
    s = np.zeros((int(m.nbody), int(m.nv)))
    s[np.asarray(m.dof_bodyid), np.arange(int(m.nv))] = 1.0
    return jnp.tensordot(jnp.asarray(s, x.dtype), x, axes=1)


def com_pos(m, d):
    """``mujoco.mjx._src.smooth.com_pos``: ``subtree_com``, ``cinert`` and ``cdof``."""
    dt = d.xipos.dtype
    mass_b = jnp.asarray(m.body_mass, dt)
    pos = _up(m, d.xipos * mass_b[:, None])
    mass = _up(m, mass_b)
    subtree_com = pos / jnp.maximum(mass, _MINVAL)[:, None]
    subtree_com = jnp.where((mass < _MINVAL)[:, None], d.xipos, subtree_com)
    d = d.replace(subtree_com=subtree_com)

    root_com = subtree_com[np.asarray(m.body_rootid)]
    offset = d.xipos - root_com
    cinert = jax.vmap(_inert_com)(jnp.asarray(m.body_inertia, dt), d.ximat, offset, mass_b)
    d = d.tree_replace({"_impl.cinert": cinert})
    return d.tree_replace({"cdof": _cdof(m, d, root_com)})


def _inert_com(inert, ximat, off, mass):
    h = jnp.cross(off, -jnp.eye(3, dtype=off.dtype))
    inert = (ximat * inert) @ ximat.T + (h @ h.T) * mass
    inert = inert[(np.array([0, 1, 2, 0, 0, 1]), np.array([0, 1, 2, 1, 2, 2]))]
    return jnp.concatenate([inert, off * mass, mass[None]])


def _cdof(m, d, root_com):
    """Motion dofs in the global frame centred at their tree's centre of mass (nv, 6)."""
    dt = root_com.dtype
    types, dadr = np.asarray(m.jnt_type), np.asarray(m.jnt_dofadr)
    jbody = np.asarray(m.jnt_bodyid)
    cdof = jnp.zeros((int(m.nv), 6), dt)
    off = root_com[jbody] - d.xanchor  # (njnt, 3)
    com = lambda a, o: jnp.concatenate([a, jnp.cross(a, o)], axis=-1)
    hinge = np.flatnonzero(types == JointType.HINGE)
    if hinge.size:
        cdof = cdof.at[dadr[hinge]].set(com(d.xaxis[hinge], off[hinge]))
    slide = np.flatnonzero(types == JointType.SLIDE)
    if slide.size:
        cdof = cdof.at[dadr[slide]].set(
            jnp.concatenate([jnp.zeros((slide.size, 3), dt), d.xaxis[slide]], axis=1))
    for j in np.flatnonzero((types == JointType.FREE) | (types == JointType.BALL)):
        rot = int(dadr[j])
        if types[j] == JointType.FREE:
            cdof = cdof.at[rot:rot + 3].set(jnp.eye(3, 6, 3, dtype=dt))
            rot += 3
        axes = d.xmat[int(jbody[j])].T  # rows: the body's axes
        cdof = cdof.at[rot:rot + 3].set(com(axes, jnp.broadcast_to(off[j], (3, 3))))
    return cdof


def crb(m, d):
    """``mujoco.mjx._src.smooth.crb``: composite inertias and the mass matrix ``M``."""
    crb_body = _up(m, d._impl.cinert).at[0].set(0.0)
    d = d.tree_replace({"_impl.crb": crb_body})
    crb_cdof = jax.vmap(_math.inert_mul)(crb_body[np.asarray(m.dof_bodyid)], d.cdof)
    qm = _support.make_m(m, crb_cdof, d.cdof, m.dof_armature)
    return d.tree_replace({"_impl.M": qm})


def _before(m) -> np.ndarray:
    """``B[i, k] = 1`` where dof ``k`` moves the frame dof ``i`` is expressed in before ``i``'s
    own joint acts: dofs of the body's ancestors and of its earlier joints (and a free joint's
    translation for its rotation dofs), as ``com_vel``'s carry accumulates them."""
    dof_body, dof_jnt = np.asarray(m.dof_bodyid), np.asarray(m.dof_jntid)
    types, dadr = np.asarray(m.jnt_type), np.asarray(m.jnt_dofadr)
    body_i, body_k = dof_body[:, None], dof_body[None, :]
    jnt_i, jnt_k = dof_jnt[:, None], dof_jnt[None, :]
    local = np.arange(int(m.nv)) - dadr[dof_jnt]  # a dof's index within its joint
    free_rotation_after_translation = ((jnt_k == jnt_i) & (types[jnt_i] == JointType.FREE)
                                       & (local[None, :] < 3) & (local[:, None] >= 3))
    earlier = np.where(body_k == body_i, jnt_k < jnt_i, _ancestors(m)[body_i, body_k] > 0)
    return (earlier | free_rotation_after_translation).astype(float)


def com_vel(m, d):
    """``mujoco.mjx._src.smooth.com_vel``: body velocities ``cvel`` and ``cdof_dot``."""
    dt = d.qvel.dtype
    v = d.cdof * d.qvel[:, None]  # (nv, 6)
    cvel = _down(m, _dof_to_body(m, v))
    before = jnp.tensordot(jnp.asarray(_before(m), dt), v, axes=1)
    cdof_dot = jax.vmap(_math.motion_cross)(before, d.cdof)
    types, dadr = np.asarray(m.jnt_type), np.asarray(m.jnt_dofadr)
    for j in np.flatnonzero(types == JointType.FREE):  # a translation has no derivative
        cdof_dot = cdof_dot.at[int(dadr[j]):int(dadr[j]) + 3].set(0.0)
    return d.tree_replace({"cvel": cvel, "cdof_dot": cdof_dot})


def rne(m, d, flg_acc: bool = False):
    """``mujoco.mjx._src.smooth.rne``: the bias forces ``qfrc_bias`` (``flg_acc``: with
    ``qacc``'s inertial term)."""
    dt = d.qvel.dtype
    if m.opt.disableflags & DisableBit.GRAVITY:
        base = jnp.zeros(6, dt)
    else:
        base = jnp.concatenate([jnp.zeros(3, dt), -jnp.asarray(m.opt.gravity, dt)])
    acc = d.cdof_dot * d.qvel[:, None]
    if flg_acc:
        acc = acc + d.cdof * d.qacc[:, None]
    cacc = base + _down(m, _dof_to_body(m, acc))

    def frc(cinert, cacc, cvel):
        f = _math.inert_mul(cinert, cacc)
        return f + _math.motion_cross_force(cvel, _math.inert_mul(cinert, cvel))

    cfrc = _up(m, jax.vmap(frc)(d._impl.cinert, cacc, d.cvel))
    qfrc_bias = jnp.sum(d.cdof * cfrc[np.asarray(m.dof_bodyid)], axis=1)
    return d.replace(qfrc_bias=qfrc_bias)


def passive(m, d):
    """``mujoco.mjx._src.passive.passive`` with tendon springs whose gradient is right at their
    rest length.

    A tendon spring pulls with ``k (lo - L)`` below its dead band ``[lo, hi]`` and ``k (hi - L)``
    above it; stock writes that as two ``where``s on ``L < lo`` and ``L > hi``, so where the band
    has no width (MuJoCo's default: both ends at the tendon's length in ``qpos0``) and ``L``
    equals it -- every rollout that starts at ``qpos0`` -- both are false and the force's
    derivative comes out 0 instead of ``-k``. The Control Suite's fish, whose fins are coupled
    by such a spring, failed gradcheck there (0.49 % on both fin roll angles). Here the force is
    ``k (clip(L, lo, hi) - L)`` with the clip taken as the constant ``lo`` when the band has no
    width: the same value everywhere, and the derivative ``-k`` at the rest length.
    """
    if not m.ntendon or m.opt.disableflags & (DisableBit.SPRING | DisableBit.DAMPER):
        return _passive.passive(m, d)
    k = m.tendon_stiffness
    d = _passive.passive(m.replace(tendon_stiffness=jnp.zeros_like(k)), d)
    lo, hi = m.tendon_lengthspring[:, 0], m.tendon_lengthspring[:, 1]
    length = d.ten_length
    rest = jnp.where(hi > lo, jnp.clip(length, lo, hi), lo)
    return d.replace(qfrc_passive=d.qfrc_passive + d._impl.ten_J.T @ (k * (rest - length)))


def fwd_velocity(m, d):
    """``mujoco.mjx._src.forward.fwd_velocity`` with ``com_vel``, ``passive`` and ``rne`` above."""
    d = d.tree_replace({
        "_impl.actuator_velocity": d._impl.actuator_moment @ d.qvel,
        "_impl.ten_velocity": d._impl.ten_J @ d.qvel,
    })
    d = com_vel(m, d)
    d = passive(m, d)
    d = rne(m, d)
    return _smooth.tendon_bias(m, d)
