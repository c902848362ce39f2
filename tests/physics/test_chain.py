"""``GeomChain``: the poses of one body's geoms from its chain's joints equal ``mjx.kinematics``,
on a model written for the test (nested, rotated frames; off-centre hinges; slides) and on the
targets of the manipulation tasks; what it cannot do (free joints) it says."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from twinrl import envs
from twinrl.physics.chain import GeomChain

XML = """
<mujoco>
  <worldbody>
    <body name="a" pos="0.1 -0.2 0.3" quat="0.9 0.1 -0.3 0.2">
      <joint name="s1" type="slide" axis="0.3 1 0.2" ref="0.05"/>
      <joint name="h1" type="hinge" axis="1 0.5 0" pos="0.02 0.03 -0.01"/>
      <geom type="box" size="0.01 0.02 0.03"/>
      <body name="b" pos="0.2 0 0.1" euler="20 -30 45">
        <joint name="h2" type="hinge" axis="0 0 1" pos="-0.05 0 0" ref="0.4"/>
        <joint name="s2" type="slide" axis="1 0 0"/>
        <geom name="g1" type="box" size="0.02 0.01 0.01" pos="0.01 0.02 0.03" euler="10 0 80"/>
        <geom name="g2" type="sphere" size="0.02" pos="-0.03 0 0.05"/>
      </body>
    </body>
    <body name="free" pos="0 0 1"><freejoint/><geom name="g3" type="sphere" size="0.1"/></body>
  </worldbody>
</mujoco>
"""


def _mjx_poses(model, mj_model, qpos, gid):
    d = mjx.kinematics(model, mjx.make_data(mj_model).replace(qpos=qpos))
    return d.geom_xpos[gid], d.geom_xmat.reshape(-1, 3, 3)[gid]


def test_chain_equals_mjx_kinematics_on_a_nested_rotated_model():
    m = mujoco.MjModel.from_xml_string(XML)
    gid = [m.geom("g1").id, m.geom("g2").id]
    chain = GeomChain(m, gid)
    assert chain.supports and sorted(chain.qpos_indices.tolist()) == [0, 1, 2, 3]
    rng = np.random.default_rng(0)
    with jax.enable_x64(True):
        model = mjx.put_model(m)  # float64 frames: the two must agree to round-off
        # jitted: one compile each, not every operation compiled on its own
        ours = lambda q: chain(model, q)  # noqa: E731
        theirs = lambda q: _mjx_poses(model, m, q, np.asarray(gid))  # noqa: E731
        poses, ref_poses = jax.jit(ours), jax.jit(theirs)
        for _ in range(5):
            qpos = jnp.asarray(m.qpos0 + rng.normal(0, 0.7, m.nq))
            xpos, xmat = poses(qpos)
            ref_pos, ref_mat = ref_poses(qpos)
            np.testing.assert_allclose(xpos, ref_pos, atol=1e-12)
            np.testing.assert_allclose(xmat, ref_mat, atol=1e-12)
        # and so do their derivatives in qpos (the pose fit's Gauss-Newton uses them)
        jac = jax.jit(jax.jacfwd(ours))(qpos)
        ref = jax.jit(jax.jacfwd(theirs))(qpos)
        for a, b in zip(jac, ref):
            np.testing.assert_allclose(a, b, atol=1e-10)
    # a body with a free joint: refused with a reason, not a wrong pose
    free = GeomChain(m, [m.geom("g3").id])
    assert not free.supports
    with pytest.raises(ValueError, match="slide and hinge"):
        free(mjx.put_model(m), jnp.asarray(m.qpos0))
    with pytest.raises(ValueError, match="share one"):
        GeomChain(m, [m.geom("g1").id, m.geom("g3").id])


@pytest.mark.parametrize("name", ["peg_insertion", "needle_threading"])
def test_chain_equals_mjx_kinematics_on_the_task_targets(name):
    # the task's own (possibly identified) mjx model: body frames come from it, not the MjModel
    env = envs.make(name)
    m, model = env.sim.mj_model, env.sim.model_with(env.params)
    gid = env.target_geom_ids
    chain = GeomChain(m, gid)
    assert chain.supports
    assert set(chain.qpos_indices.tolist()) <= set(np.asarray(m.jnt_qposadr)[
        list(env.target_joints)].tolist())
    rng = np.random.default_rng(1)
    ours, theirs = jax.jit(lambda q: chain(model, q)), jax.jit(lambda q: _mjx_poses(
        model, m, q, gid))
    for _ in range(3):
        qpos = jnp.asarray(m.qpos0 + rng.normal(0, 0.1, m.nq), jnp.float32)
        xpos, xmat = ours(qpos)
        ref_pos, ref_mat = theirs(qpos)
        np.testing.assert_allclose(xpos, ref_pos, atol=2e-6)
        np.testing.assert_allclose(xmat, ref_mat, atol=2e-6)
