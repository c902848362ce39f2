"""A tendon spring at its rest length: stock MJX's dead-band ``where``s give its force a zero
derivative there (both tests false when the band has no width), so every rollout starting at
``qpos0`` had a wrong gradient along the spring; twinrl's ``smooth.passive`` gives ``-k J^T J``."""

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
from mujoco.mjx._src import passive as stock_passive

from tests.physics._foreign import FOREIGN
from twinrl.physics import Sim, smooth
from twinrl.physics.gradcheck import gradcheck

SCENE = FOREIGN / "tendon_spring.xml"


@functools.partial(jax.jit, static_argnums=0)
def _passive_force(passive, m, qpos):
    d = mjx.make_data(m).replace(qpos=qpos)
    d = mjx.kinematics(m, d)
    d = mjx.com_pos(m, d)
    d = mjx.tendon(m, d)
    return passive(m, d).qfrc_passive


def test_tendon_spring_force_equals_stock_and_its_derivative_at_rest_length_is_minus_k_JtJ(x64):
    mj = mujoco.MjModel.from_xml_path(str(SCENE))
    m = mjx.put_model(mj)
    qpos0 = jnp.asarray(mj.qpos0)
    # the same force as stock on and off the rest length
    for q in (qpos0, qpos0 + jnp.array([0.3, -0.1]), qpos0 + jnp.array([-0.2, -0.4])):
        np.testing.assert_allclose(_passive_force(smooth.passive, m, q),
                                   _passive_force(stock_passive.passive, m, q), atol=1e-15)
    sym = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_TENDON, "sym")
    k = mj.tendon_stiffness[sym]
    J = np.zeros(mj.nv)
    J[[mj.jnt_dofadr[mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_JOINT, n)]
       for n in ("left", "right")]] = 0.5
    expected = -k * np.outer(J, J)
    ours = jax.jacfwd(lambda q: _passive_force(smooth.passive, m, q))(qpos0)
    stock = jax.jacfwd(lambda q: _passive_force(stock_passive.passive, m, q))(qpos0)
    np.testing.assert_allclose(ours, expected, atol=1e-15)
    assert np.all(np.asarray(stock) == 0)  # stock's, for the record: the defect fixed here
    # central differences of the force agree with ours
    h = 1e-6
    fd = np.stack([(_passive_force(smooth.passive, m, qpos0 + h * e)
                    - _passive_force(smooth.passive, m, qpos0 - h * e)) / (2 * h)
                   for e in np.eye(mj.nv)], axis=1)
    np.testing.assert_allclose(fd, expected, atol=1e-10)


def test_rollout_from_rest_length_passes_gradcheck_and_matches_stock_forward(x64):
    with jax.enable_x64(True):
        sim = Sim.load(SCENE)
        actions = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (20, sim.nu)))
        ours = jax.jit(lambda a: sim.rollout(sim.init(), a)[1])(actions)
        stock = jax.jit(lambda a: sim.rollout(sim.init(), a, step_fn=sim.stock_step)[1])(actions)
        np.testing.assert_allclose(ours.qpos, stock.qpos, atol=1e-12)
        r = gradcheck(sim, horizon=20, scenario="wave")
    assert r.nan_count == 0 and r.failures == [], r.failures[:3]
    qpos = next(g for g in r.groups if g["group"] == "qpos")
    assert qpos["resolved"] == sim.nv and r.max_rel_error <= 1e-4
