"""``contacts="mujoco"``: a box on a plane touches as in MuJoCo C (every lower corner), where stock
MJX keeps only the corners within 1 mm of the deepest one. Checked against MuJoCo C itself."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
import pytest

from tests.physics._foreign import FOREIGN, check_foreign_scene
from twinrl import envs
from twinrl.physics import Sim
from twinrl.physics import collision


def _quat(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    h = np.radians(deg) / 2
    return np.concatenate([[np.cos(h)], np.sin(h) * axis])


def _rocking_poses(n=12, seed=0):
    """Box poses tilted 1-8 degrees about a random horizontal axis, the lowest corner 0.5-4 mm
    into the floor: the corners are at different depths, as when a pushed box rocks."""
    rng = np.random.default_rng(seed)
    half = np.array([0.05, 0.04, 0.03])  # box_sliding.xml's box
    poses = []
    for _ in range(n):
        ang = rng.uniform(0, 2 * np.pi)
        tilt = _quat([np.cos(ang), np.sin(ang), 0.0], rng.uniform(1.0, 8.0))
        q = np.empty(4)
        mujoco.mju_mulQuat(q, tilt, _quat([0, 0, 1], rng.uniform(-180, 180)))
        mat = np.empty(9)
        mujoco.mju_quat2Mat(mat, q)
        lowest = np.min(np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1)
                                  for sz in (-1, 1)]) * half @ mat.reshape(3, 3).T[:, 2])
        z = -lowest - rng.uniform(0.0005, 0.004)
        poses.append(np.concatenate([rng.uniform(-0.1, 0.1, 2), [z], q]))
    return poses


@pytest.fixture(scope="module")
def scene(x64):
    m = mujoco.MjModel.from_xml_path(str(FOREIGN / "box_sliding.xml"))
    m.opt.iterations, m.opt.ls_iterations = 50, 50  # both engines converge their solve
    return m


def _contacts_c(m, qpos):
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    return sorted((round(c.pos[0], 9), round(c.pos[1], 9), c.pos[2], c.dist)
                  for c in d.contact[:d.ncon])


def test_box_on_plane_contacts_equal_mujoco_c(scene):
    # The contacts the constraint stage activates (distance below the margin, here 0): the same
    # points and depths as MuJoCo C's; stock MJX's miss some of them on rocking boxes.
    mx = mjx.put_model(scene)
    pos_stage = {rule: jax.jit(lambda d, r=rule: collision.fwd_position(mx, d, r))
                 for rule in collision.CONTACTS}
    fewer = 0
    for qpos in _rocking_poses():
        want = _contacts_c(scene, qpos)
        assert len(want) >= 1
        got = {}
        for rule, f in pos_stage.items():
            c = f(mjx.make_data(mx).replace(qpos=jnp.asarray(qpos)))._impl.contact
            active = np.asarray(c.dist) < 0
            got[rule] = sorted((p[0], p[1], p[2], dd) for p, dd in
                               zip(np.asarray(c.pos)[active], np.asarray(c.dist)[active]))
            # the normal is the plane's for every contact
            normals = np.asarray(c.frame)[active][:, 0]
            np.testing.assert_allclose(normals, np.tile([0.0, 0.0, 1.0], (len(normals), 1)),
                                       atol=1e-12)
        assert len(got["mujoco"]) == len(want)
        np.testing.assert_allclose(np.array(got["mujoco"]), np.array(want), atol=1e-9)
        fewer += len(got["mjx"]) < len(want)
    assert fewer >= 3  # the poses do exercise the difference


def test_rocking_box_steps_as_mujoco_c_with_the_mujoco_rule(scene):
    # 20 physics steps (0.1 s) of a box sliding and rocking from each pose: MuJoCo C's mj_step
    # against the differentiable step with each rule (same model, converged solves).
    sims = {rule: Sim(mj_model=scene, model=mjx.put_model(scene), contacts=rule)
            for rule in collision.CONTACTS}
    roll = {rule: jax.jit(lambda q, v, s=s: s.rollout(s.init(q, v), jnp.zeros((20, 0)))[0])
            for rule, s in sims.items()}
    worst = dict.fromkeys(sims, 0.0)
    d = mujoco.MjData(scene)
    for qpos in _rocking_poses(6, seed=1):
        qvel = np.array([0.5, 0.1, 0.0, 0.0, 0.0, 0.5])
        mujoco.mj_resetData(scene, d)
        d.qpos[:], d.qvel[:] = qpos, qvel
        for _ in range(20):
            mujoco.mj_step(scene, d)
        for rule, f in roll.items():
            out = f(jnp.asarray(qpos), jnp.asarray(qvel))
            worst[rule] = max(worst[rule], float(np.max(np.abs(np.asarray(out.qvel) - d.qvel))))
    assert worst["mujoco"] <= 1e-6, worst
    assert worst["mjx"] >= 1e-3, worst  # what the rule changes is not rounding


def test_box_drop_gradients_with_the_mujoco_rule(x64):
    # The tilted drop lands corner by corner: each corner's contact switches on as it touches.
    check_foreign_scene("box_drop", contacts="mujoco")


def test_bad_contacts_and_iterations_are_one_line_errors():
    with pytest.raises(ValueError, match="contacts must be one of mjx, mujoco, got 'bullet'"):
        Sim.load("push", contacts="bullet")
    with pytest.raises(ValueError, match="contacts must be one of mjx, mujoco"):
        envs.make("push", contacts="C")
    with pytest.raises(ValueError, match="solver_iterations must be >= 1, got 0"):
        envs.make("push", solver_iterations=0)
    e = envs.make("push", contacts="mujoco", solver_iterations=12)
    assert e.sim.contacts == "mujoco" and e.sim.mj_model.opt.iterations == 12
    assert e.sim.recompiled(e.sim.mj_model).contacts == "mujoco"
