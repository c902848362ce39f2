"""PhysParams: shapes, validation, reparameterisation, application to the MJX model."""

import jax
import mujoco
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from twinrl.physics import PhysParams, Sim


@pytest.fixture(scope="module")
def push():
    return Sim.load("push")


def test_from_model_shapes(push):
    p = push.default_params()
    m = push.mj_model
    assert p.mass.shape == (m.nbody - 1,)
    assert p.damping.shape == p.armature.shape == p.frictionloss.shape == (m.nv,)
    assert p.friction.shape == (m.ngeom,)
    assert p.gain.shape == (m.nu,) and p.bias.shape == (m.nu, 3) and p.gravity.shape == (3,)
    np.testing.assert_allclose(p.mass, [0.2, 0.5])


@pytest.mark.parametrize("field, value, match", [
    ("mass", -1.0, r"mass must be > 0, got -1.0"),
    ("friction", -0.5, r"friction must be > 0"),
    ("damping", -0.1, r"damping must be >= 0"),
    ("gain", np.nan, r"gain has a non-finite value"),
    ("gravity", np.inf, r"gravity has a non-finite value"),
])
def test_bad_values_raise_naming_the_field(push, field, value, match):
    p = push.default_params()
    bad = np.array(getattr(p, field)).copy()
    bad.flat[0] = value
    with pytest.raises(ValueError, match=match):
        p.replace(**{field: jnp.asarray(bad)})


def test_reparameterisation_round_trip_and_always_valid(push):
    p = push.default_params()
    back = PhysParams.constrain(p.unconstrain())
    for k, v in p.as_dict().items():
        np.testing.assert_allclose(back.as_dict()[k], v, rtol=1e-5, atol=1e-8)
    raw = jax.tree_util.tree_map(lambda x: -50.0 * jnp.ones_like(x), p.unconstrain())
    q = PhysParams.constrain(raw)  # arbitrary reals -> valid parameters (constructor checks)
    assert float(q.mass.min()) > 0 and float(q.damping.min()) >= 0


def test_apply_writes_every_field_and_scales_inertia(push):
    p = push.default_params().scaled(mass=2.0, damping=3.0, friction=0.5, gain=1.5)
    p = p.replace(gravity=jnp.array([0.0, 0.0, -5.0]), armature=p.armature + 0.01,
                  frictionloss=p.frictionloss + 0.02, bias=p.bias + 0.1)
    m0, m = push.model, p.apply(push.model)
    np.testing.assert_allclose(m.body_mass[1:], 2 * np.asarray(m0.body_mass[1:]), rtol=1e-6)
    np.testing.assert_allclose(m.body_inertia[1:], 2 * np.asarray(m0.body_inertia[1:]), rtol=1e-6)
    np.testing.assert_allclose(m.dof_damping, 3 * np.asarray(m0.dof_damping), rtol=1e-6)
    np.testing.assert_allclose(m.dof_armature, np.asarray(m0.dof_armature) + 0.01, rtol=1e-6)
    np.testing.assert_allclose(m.dof_frictionloss, np.asarray(m0.dof_frictionloss) + 0.02, rtol=1e-6)
    np.testing.assert_allclose(m.geom_friction[:, 0], 0.5 * np.asarray(m0.geom_friction[:, 0]), rtol=1e-6)
    np.testing.assert_allclose(m.actuator_gainprm[:, 0], 1.5 * np.asarray(m0.actuator_gainprm[:, 0]), rtol=1e-6)
    np.testing.assert_allclose(m.actuator_biasprm[:, :3], np.asarray(m0.actuator_biasprm[:, :3]) + 0.1, rtol=1e-6)
    np.testing.assert_allclose(m.opt.gravity, [0, 0, -5])
    # and the dynamics see them: heavier box under weaker gravity falls slower
    d = push.init(np.r_[0, 0, 0.15, 0, 0.3, 1, 0, 0, 0])
    box_z = jax.jit(lambda q: push.rollout(d, jnp.zeros((10, 2)), q)[1].qpos[-1, 4])
    z_nominal = box_z(push.default_params())
    z_changed = box_z(p)
    assert float(z_changed) > float(z_nominal)


def test_gradient_trees_are_not_validated(push):
    # Cotangents of PhysParams are PhysParams-shaped and may be negative or zero.
    p = push.default_params()
    g = jax.grad(lambda q: -jnp.sum(q.mass) - jnp.sum(q.friction))(p)
    assert isinstance(g, PhysParams) and float(g.mass[0]) == -1.0


@pytest.mark.parametrize("field, value, match", [
    ("mass", jnp.zeros((0,)), r"PhysParams.mass has shape \(0,\); push needs \(2,\) \(nbody-1"),
    ("mass", jnp.ones((3,)), r"PhysParams.mass has shape \(3,\); push needs \(2,\)"),
    ("bias", jnp.ones((1,)), r"PhysParams.bias has shape \(1,\); push needs \(2, 3\)"),
    ("gravity", jnp.ones(()), r"PhysParams.gravity has shape \(\); push needs \(3,\)"),
])
def test_shapes_are_checked_against_a_model_naming_the_field(push, field, value, match):
    p = push.default_params()
    assert p.check_shapes(push.mj_model) is p
    with pytest.raises(ValueError, match=match):
        p.replace(**{field: value}).check_shapes(push.mj_model, "push")


MOUNT = """<mujoco><worldbody><body name="mount" pos="0 0 1">
    <body name="link"><joint type="hinge" axis="1 0 0"/><geom size="0.1" pos="0 0.2 0"/></body>
    </body><body name="frame" pos="1 0 0"><site name="s"/></body></worldbody></mujoco>"""


def test_a_massless_frame_stays_massless_and_changes_nothing():
    """MuJoCo allows a body without dofs to have no mass (a mount, a frame for a site): its mass
    is the model's 0, kept by from_model, written as 0 by apply and to_mjmodel whatever the field
    holds, with zero derivative; check_shapes refuses a 0 anywhere the model has none."""
    sim = Sim.load(MOUNT)
    p = sim.default_params()
    np.testing.assert_allclose(p.mass, [0.0, sim.mj_model.body_mass[2], 0.0])
    back = PhysParams.constrain(p.unconstrain())  # finite both ways, the zeros come back tiny
    assert np.all(np.isfinite(np.asarray(p.unconstrain()["mass"])))
    assert float(back.mass[0]) < 1e-8
    bumped = p.replace(mass=p.mass.at[0].set(5.0))
    np.testing.assert_array_equal(np.asarray(bumped.apply(sim.model).body_mass), sim.model.body_mass)
    assert bumped.to_mjmodel(sim.mj_model).body_mass[1] == 0.0
    d = sim.init(jnp.array([0.3]))

    def final_angle(q):
        return sim.rollout(d, jnp.zeros((20, 0)), q)[1].qpos[-1, 0]

    g = jax.grad(final_angle)(p)
    assert float(g.mass[0]) == 0.0 and float(g.mass[2]) == 0.0
    assert float(final_angle(bumped)) == float(final_angle(p))
    with pytest.raises(ValueError, match=r"^PhysParams.mass\[1\] is 0 where this model has "):
        p.replace(mass=p.mass.at[1].set(0.0)).check_shapes(sim.mj_model)


def test_an_empty_mjcf_path_says_so():
    with pytest.raises(ValueError, match=r"the MJCF path is empty"):
        Sim.load("")


def test_a_geom_pair_mjx_cannot_collide_is_one_line_naming_the_geoms():
    """MJX 3.17 has no collision of two height fields (nor twinrl): its ``put_model`` raises
    NotImplementedError, which a user's scene should meet as one MJCFError naming the geoms,
    not a traceback."""
    from twinrl.physics import MJCFError

    xml = """<mujoco><asset><hfield name="h" nrow="2" ncol="2" size="0.1 0.1 0.02 0.01"
          elevation="0 0 0 0"/></asset>
        <worldbody><geom name="floor" type="plane" size="1 1 0.1"/>
        <geom name="ground" type="hfield" hfield="h" pos="0.5 0 0"/>
        <body name="tile" pos="0 0 0.03"><freejoint/><geom type="hfield" hfield="h" mass="1"/>
        </body>
        <body name="can" pos="0 0 0.12"><freejoint/><geom type="cylinder" size="0.03 0.04"/>
        </body></worldbody></mujoco>"""
    with pytest.raises(NotImplementedError):  # the stock call's behaviour this wraps
        mjx.put_model(mujoco.MjModel.from_xml_string(xml))
    with pytest.raises(MJCFError, match=r"^mjcf: MJX \(mujoco [\d.]+\) has no collision function "
                                        r"for hfield 'ground' x hfield #2 of body 'tile': ") as e:
        Sim.load(xml)
    assert "\n" not in str(e.value)
    with pytest.raises(MJCFError,
                       match=r"cannot simulate this model: .*PGS is not implemented there$"):
        Sim.load(xml.replace("<mujoco>", "<mujoco><option solver='PGS'/>")
                 .replace('<geom type="hfield" hfield="h" mass="1"/>',
                          '<geom type="box" size="0.1 0.1 0.01"/>'))


def test_to_mjmodel_writes_what_apply_writes_into_mjx():
    """``PhysParams.to_mjmodel`` (MuJoCo C, saved MJCF) and ``apply`` (MJX) write the same
    values; a non-negative field at the reparameterisation's floor is written as 0."""
    sim = Sim.load("push")
    p = sim.default_params()
    p = p.replace(mass=p.mass * 1.3, damping=p.damping * 0.5 + 0.1, friction=p.friction * 0.8,
                  gain=p.gain * 1.1, frictionloss=jnp.full_like(p.frictionloss, 1e-9))
    m = p.to_mjmodel(sim.mj_model)
    stock = p.apply(sim.model)
    for c, x in (("body_mass", "body_mass"), ("body_inertia", "body_inertia"),
                 ("dof_damping", "dof_damping"), ("geom_friction", "geom_friction"),
                 ("actuator_gainprm", "actuator_gainprm"), ("actuator_biasprm", "actuator_biasprm")):
        np.testing.assert_allclose(getattr(m, c), np.asarray(getattr(stock, x)), rtol=1e-6,
                                   err_msg=c)
    assert np.all(m.dof_frictionloss == 0)
    assert np.all(sim.mj_model.body_mass == Sim.load("push").mj_model.body_mass)  # a copy
