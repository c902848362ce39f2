"""Contacts of one geom placed against MuJoCo C's: shared by the tests of ``twinrl.physics.hfield``
and ``twinrl.physics.polytopes``."""

import jax
import mujoco
import numpy as np
from mujoco import mjx

from twinrl.physics import Sim, collision


class Placer:
    """Places one body of a scene (the others out of reach, high above, but those in ``fixed``
    left at their ``qpos0``) so that MuJoCo C's deepest contact of its geom is 2 mm deep, then
    returns C's contacts of that geom and twinrl's (float64) at the same state. ``heights``:
    a range of heights of the body, penetrating at its start, clear at its end."""

    def __init__(self, path, fixed=(), heights=(-0.5, 1.0)):
        self.fixed, self.heights = fixed, heights
        self.sim = Sim.load(path)
        self.m = self.sim.mj_model
        self.d = mujoco.MjData(self.m)
        self.fwd = jax.jit(lambda d: collision.fwd_position(self.sim.model, d))

    def __call__(self, body, xy, euler, depth=0.002):
        m, d = self.m, self.d
        d.qpos[:] = m.qpos0
        for b in range(1, m.nbody):  # every other free body high above
            if m.body(b).name not in self.fixed:
                d.qpos[m.jnt_qposadr[m.body_jntadr[b]]:][:3] = [0.0, 0.0, 3.0 + b]
        adr = m.jnt_qposadr[m.body_jntadr[m.body(body).id]]
        mujoco.mju_euler2Quat(d.qpos[adr + 3:adr + 7], np.radians(euler), "xyz")
        g = m.geom(body).id
        lo, hi = self.heights  # deep in, clear above
        for _ in range(60):  # bisection on the height: C's deepest contact at -depth
            d.qpos[adr:adr + 3] = [*xy, 0.5 * (lo + hi)]
            mujoco.mj_forward(m, d)
            if min([c.dist for c in d.contact[:d.ncon] if g in c.geom], default=1.0) < -depth:
                lo = 0.5 * (lo + hi)
            else:
                hi = 0.5 * (lo + hi)
        d.qpos[adr:adr + 3] = [*xy, hi]
        mujoco.mj_forward(m, d)
        theirs = [(c.dist, c.pos.copy(), c.frame[:3].copy()) for c in d.contact[:d.ncon]
                  if g in c.geom]
        with collision.mjx_pairs():  # put_data sizes contacts by MJX's table
            data = mjx.put_data(m, d)
        c = self.fwd(data)._impl.contact
        mine = np.any(np.asarray(c.geom) == g, axis=1)
        ours = (np.asarray(c.dist)[mine], np.asarray(c.pos)[mine],
                np.asarray(c.frame)[mine, 0])
        return theirs, ours


def nearest(ours, pos):
    """Our contact nearest to ``pos``: (dist, position error, normal of ours)."""
    dist, p, n = ours
    j = int(np.argmin(np.linalg.norm(p - pos, axis=1)))
    return dist[j], float(np.linalg.norm(p[j] - pos)), n[j]


def angle(a, b):
    return float(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))))


def positions_against_mujoco(sim, T):
    """``(ours, theirs, traj)``: every free body's position over ``T`` unactuated steps of
    ``sim`` (a rollout from ``sim.init()``) and of MuJoCo C from the same start, (T, bodies, 3)."""
    import jax.numpy as jnp

    m, d = sim.mj_model, mujoco.MjData(sim.mj_model)
    theirs = []
    for _ in range(T):
        mujoco.mj_step(m, d)
        theirs.append(d.qpos.copy())
    theirs = np.array(theirs).reshape(T, -1, 7)[:, :, :3]
    _, traj = jax.jit(lambda d: sim.rollout(d, jnp.zeros((T, 0))))(sim.init())
    return np.asarray(traj.qpos).reshape(T, -1, 7)[:, :, :3], theirs, traj
