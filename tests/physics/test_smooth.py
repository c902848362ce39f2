"""``twinrl.physics.smooth`` equals the stock ``mjx`` stages it replaces (kinematics, ``com_pos``,
``crb``, ``com_vel``, ``rne``, ``fwd_velocity``), forward and gradient, in float64, on a model
written to exercise every joint type, nesting, rotated frames, several joints on one body,
off-centre joint anchors, mocap bodies, sites and inertial frames -- and on the manipulation
tasks' arm (peg insertion)."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx
from mujoco.mjx._src import forward as stock_forward
from mujoco.mjx._src import smooth as stock

from twinrl import envs
from twinrl.physics import smooth

XML = """<mujoco><worldbody>
<body name="mc" mocap="true" pos="0.1 0 0.3" quat="0.9 0.1 0 0.2"><geom size=".02"/></body>
<body pos="0.1 0.2 0.3" quat="0.8 0.2 0.3 0.1">
 <joint type="hinge" axis="0.3 0.4 0.5" pos="0.1 0 0"/>
 <joint type="slide" axis="1 0.2 0" pos="0 0.1 0"/>
 <geom type="box" size=".1 .05 .02" pos="0.05 0 0" quat="0.9 0 0.3 0"/>
 <site name="s" pos="0.1 0.1 0" quat="0.5 0.5 0.5 0.5"/>
 <body pos="0 0.3 0" quat="0.7 0 0.7 0"><joint type="ball" pos="0.02 0.01 0"/>
  <geom type="capsule" size=".02 .1"/>
  <body pos="0.2 0 0"><geom size=".03"/></body>
  <body pos="0 0 0.2"><joint type="hinge" axis="0 1 0"/>
   <joint type="hinge" axis="1 0 0" pos="0 0 0.05"/><geom size=".03" pos="0 0 .1"/></body>
 </body></body>
<body pos="1 0 1"><freejoint/><geom type="box" size=".05 .05 .05" pos="0.01 0 0"/>
 <inertial pos="0.01 0.02 0" quat="0.9 0.1 0.1 0.1" mass="1" diaginertia="0.01 0.02 0.03"/>
</body></worldbody></mujoco>"""

KINEMATICS = ["qpos", "xanchor", "xaxis", "xpos", "xquat", "xmat", "xipos", "ximat", "geom_xpos",
              "geom_xmat", "site_xpos", "site_xmat"]
# stage, ours, stock, the fields it writes
STAGES = [(smooth.com_pos, stock.com_pos, ["subtree_com", "_impl.cinert", "cdof"]),
          (smooth.crb, stock.crb, ["_impl.crb", "_impl.M"]),
          (smooth.com_vel, stock.com_vel, ["cvel", "cdof_dot"]),
          (smooth.rne, stock.rne, ["qfrc_bias"]),
          (smooth.fwd_velocity, stock_forward.fwd_velocity,
           ["qfrc_bias", "qfrc_passive", "cvel", "cdof_dot", "_impl.actuator_velocity"])]


def _get(d, field):
    return getattr(d._impl, field[6:]) if field.startswith("_impl.") else getattr(d, field)


def _models():
    yield "every joint type", mujoco.MjModel.from_xml_string(XML)
    yield "peg_insertion", envs.make("peg_insertion").sim.mj_model


@pytest.fixture(scope="module")
def models(x64):
    return list(_models())


def _random_qpos(mj, rng):
    return mj.qpos0 + rng.normal(0, 0.5, mj.nq)


def test_kinematics_equals_stock_forward_and_gradient(models):
    rng = np.random.default_rng(0)
    for name, mj in models:
        m = mjx.put_model(mj)

        def fields(kin, qpos, mocap_pos, mocap_quat):
            d = mjx.make_data(m).replace(qpos=qpos, mocap_pos=mocap_pos, mocap_quat=mocap_quat)
            d = kin(m, d)
            return [_get(d, f) for f in KINEMATICS]

        def loss(kin, *args):
            return sum(jnp.sum(jnp.sin((i + 1) * x)) for i, x in enumerate(fields(kin, *args)))

        ours = jax.jit(lambda *a: (fields(smooth.kinematics, *a),
                                   jax.grad(lambda q: loss(smooth.kinematics, q, *a[1:]))(a[0])))
        ref = jax.jit(lambda *a: (fields(stock.kinematics, *a),
                                  jax.grad(lambda q: loss(stock.kinematics, q, *a[1:]))(a[0])))
        for _ in range(3):
            args = (jnp.asarray(_random_qpos(mj, rng)),
                    jnp.asarray(rng.normal(size=(mj.nmocap, 3))),
                    jnp.asarray(rng.normal(size=(mj.nmocap, 4))))
            (a, g), (b, g_ref) = ours(*args), ref(*args)
            for f, x, y in zip(KINEMATICS, a, b):
                np.testing.assert_allclose(x, y, atol=1e-12, err_msg=f"{name} {f}")
            assert np.abs(g_ref).max() > 1e-3, name  # the loss depends on qpos
            np.testing.assert_allclose(g, g_ref, rtol=1e-10, atol=1e-10, err_msg=name)


def test_tree_stages_equal_stock_forward_and_gradient(models):
    rng = np.random.default_rng(1)
    for name, mj in models:
        m = mjx.put_model(mj)
        c = mujoco.MjData(mj)  # every stage's inputs, from MuJoCo C (no compile)
        c.qpos, c.qvel = _random_qpos(mj, rng), rng.normal(0, 1.0, mj.nv)
        mujoco.mj_forward(mj, c)
        d = mjx.put_data(mj, c)

        def outputs(stages, d):
            return [[_get(stage(m, d), f) for f in fields] for stage, fields in stages]

        # the gradient of the position and velocity stages' outputs w.r.t. the state they read
        def loss(stages, qvel, xipos):
            e = d.replace(qvel=qvel, xipos=xipos)
            for stage in stages:
                e = stage(m, e)
            return (jnp.sum(jnp.sin(e.qfrc_bias)) + jnp.sum(jnp.cos(e._impl.M))
                    + jnp.sum(jnp.sin(e.cvel)) + jnp.sum(jnp.sin(e.cdof_dot)))

        def run(stages, chain):
            return jax.jit(lambda d: (outputs(stages, d), jax.grad(
                lambda *a: loss(chain, *a), argnums=(0, 1))(d.qvel, d.xipos)))(d)

        a, g = run([(s[0], s[2]) for s in STAGES],
                   (smooth.com_pos, smooth.crb, smooth.fwd_velocity))
        b, g_ref = run([(s[1], s[2]) for s in STAGES],
                       (stock.com_pos, stock.crb, stock_forward.fwd_velocity))
        for (stage, _, fields), xs, ys in zip(STAGES, a, b):
            for f, x, y in zip(fields, xs, ys):
                np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-12,
                                           err_msg=f"{name} {stage.__name__} {f}")
        for x, y in zip(g, g_ref):
            assert np.abs(y).max() > 1e-6, name
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-10, err_msg=name)


def test_quaternion_contractions_equal_stock_math():
    from mujoco.mjx._src import math as mjx_math
    rng = np.random.default_rng(2)
    for _ in range(5):
        u, v = rng.normal(size=4), rng.normal(size=4)
        np.testing.assert_allclose(smooth.quat_mul(jnp.asarray(u), jnp.asarray(v)),
                                   mjx_math.quat_mul(jnp.asarray(u), jnp.asarray(v)), atol=1e-6)
        q = u / np.linalg.norm(u)
        np.testing.assert_allclose(smooth.quat_to_mat(jnp.asarray(q)),
                                   mjx_math.quat_to_mat(jnp.asarray(q)), atol=1e-6)
