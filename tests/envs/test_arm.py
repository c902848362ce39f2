"""The manipulation suite's robot: Panda kinematics equal to its MJCF, a Cartesian controller that
moves the tool where it is told, a camera mount whose differentiable images equal the real twin's
OpenGL frames, and tasks whose success a scripted expert reaches in the simulator and in the real
twin.

(The parameterised tests over every task -- jit, no NaN, gradients, Brax PPO, the real twin's
check_env, determinism and zero-perturbation agreement -- live in tests/envs/test_envs.py,
tests/envs/test_ppo.py and tests/real/test_twin.py and take these tasks by registration.)
"""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from twinrl import envs
from twinrl.envs.arm import kinematics as arm
from twinrl.real.perturbation import Perturbation
from twinrl.real.twin import RealTwin

ARM_TASKS = ("peg_insertion", "spatula_flipping", "needle_threading")
# Distance (m) between the tool's end in the simulator and in the unperturbed real twin after the
# scripted expert's episode replayed open loop (through tool-object contact; measured below).
# (Spatula measured 2.0 mm at reset key 2 with the capsule pancake, 5.2 mm with the box one; where
# in the episode the gap opens was not isolated.)
ZERO_TWIN_TOOL_TOL = {"peg_insertion": 2e-3, "spatula_flipping": 4e-3, "needle_threading": 2e-3}
# The reset key of the expert's episode. The peg, spatula and needle experts succeed from every
# start tried (8 of 8, keys 0-7); for the spatula this test is about the engines agreeing through
# a flip (slide under, lift, fall over the rail).
EXPERT_START = {"peg_insertion": 1, "spatula_flipping": 2, "needle_threading": 1}


@pytest.fixture(scope="module")
def made():
    return {name: envs.make(name) for name in ARM_TASKS}


def test_kinematics_equal_the_mjcf_and_its_jacobian():
    m = mujoco.MjModel.from_xml_path(str(arm.ARM_XML))
    d = mujoco.MjData(m)
    site = m.site("tool_mount").id
    fk = jax.jit(arm.forward_kinematics)
    jac = jax.jit(arm.jacobian)
    rng = np.random.default_rng(0)
    for q in rng.uniform(arm.JOINT_RANGE[:, 0], arm.JOINT_RANGE[:, 1], size=(5, 7)):
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        p, R = fk(jnp.asarray(q, jnp.float32))
        np.testing.assert_allclose(p, d.site_xpos[site], atol=2e-6)
        np.testing.assert_allclose(R, d.site_xmat[site].reshape(3, 3), atol=2e-6)
        jp, jr = np.zeros((3, 7)), np.zeros((3, 7))
        mujoco.mj_jacSite(m, d, jp, jr, site)
        np.testing.assert_allclose(jac(jnp.asarray(q, jnp.float32)), np.vstack([jp, jr]),
                                   atol=2e-6)
    # Franka's published 'ready' pose: flange at (0.307, 0, 0.590), pointing down
    _, _, p, R = arm.joint_frames(jnp.asarray(arm.HOME, jnp.float32))
    np.testing.assert_allclose(p, [0.3069, 0.0, 0.5903], atol=2e-4)
    np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-6)


def test_ik_reaches_a_pose_and_says_when_none_reaches_it():
    q = arm.solve_ik([0.5, 0.1, 0.2], tcp=(0.0, 0.0, 0.1))
    p, R = arm.forward_kinematics(jnp.asarray(q, jnp.float32), (0.0, 0.0, 0.1))
    np.testing.assert_allclose(p, [0.5, 0.1, 0.2], atol=1e-4)
    np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-3)
    assert np.all(q >= arm.JOINT_RANGE[:, 0]) and np.all(q <= arm.JOINT_RANGE[:, 1])
    with pytest.raises(ValueError, match="no joint posture of the arm reaches"):
        arm.solve_ik([2.0, 0.0, 0.2])


@pytest.mark.parametrize("name", ARM_TASKS)
def test_controller_moves_the_tool_where_it_is_told(name, made):
    env = made[name]
    step = jax.jit(env.step)
    s0 = env.reset(jax.random.PRNGKey(0))
    p0 = np.asarray(env.tool_point(s0.pipeline_state.qpos))
    for axis in range(3):
        a = np.zeros(env.action_size, np.float32)
        a[axis] = 1.0 if axis < 2 else 0.5
        s = s0
        for _ in range(3):
            s = step(s, a)
        move = np.asarray(env.tool_point(s.pipeline_state.qpos)) - p0
        # along the commanded axis, the servos' lag short of 3 full steps (measured: at least 0.27
        # of the commanded distance from rest; off-axis drift under a third of the move)
        assert move[axis] > 0.2 * 3 * env.controller.max_step * a[axis], (name, axis, move)
        assert abs(move[axis]) > 2.5 * np.abs(np.delete(move, axis)).max(), (name, axis, move)
    if env.controller.yaw:
        turn = np.array([0, 0, 0, 1.0], np.float32)
        s = s0
        for _ in range(3):
            s = step(s, turn)
        h = lambda st: float(arm.heading(
            arm.forward_kinematics(st.pipeline_state.qpos[:7], env.controller.tcp)[1],
            env.controller.nominal))
        assert h(s) - h(s0) > 0.1, (h(s0), h(s))


def test_camera_mount_stays_in_its_workspace_and_looks_at_its_target(made):
    mount = made["peg_insertion"].mount
    for coords in ([0.0, 0.0, 0.0], [30.0, -30.0, 5.0], [-3.0, 2.0, -40.0]):
        c = jnp.asarray(coords, jnp.float32)
        az, el, dist = np.asarray(mount.spherical(c))
        assert mount.azimuth[0] <= az <= mount.azimuth[1]
        assert mount.elevation[0] <= el <= mount.elevation[1]
        assert mount.distance[0] <= dist <= mount.distance[1]
        eye, R = np.asarray(mount.eye(c)), np.asarray(mount.xmat(c))
        np.testing.assert_allclose(np.linalg.norm(eye - mount.target), dist, rtol=1e-5)
        # the camera looks down its -z axis, at the target, with the world's up in its image up
        np.testing.assert_allclose(-R[:, 2], (mount.target - eye) / dist, atol=1e-5)
        assert R[2, 1] > 0 and abs(R[2, 0]) < 1e-5
    assert mount.steps_to_move([0, 0, 0], [0, 0, 0]) == 0
    assert mount.steps_to_move([-5, 0, 0], [5, 0, 0]) == int(
        np.ceil(np.ptp(mount.azimuth) * 0.98 / mount.max_speed))
    with pytest.raises(ValueError, match="outside the mount's workspace"):
        mount.coords_of([10.0, 0.5, 0.5])


@pytest.mark.parametrize("name", ARM_TASKS)
def test_rendered_mount_views_equal_the_real_twins_opengl_frames(name, made):
    """twinrl.render (differentiable) and the real twin's OpenGL camera agree at mount poses."""
    env = made[name]
    n = env.config.image_size  # the size the loop records and deploys at
    twin = RealTwin(name, perturbation=Perturbation.none(), width=n, height=n)
    twin.reset(seed=3)
    o = twin.oracle()
    state = env.reset(jax.random.PRNGKey(0))
    state = state.replace(pipeline_state=env.sim.init(o.qpos, o.qvel))
    render = jax.jit(lambda s, c: env.render(s, c))
    for coords in ([0.0, 0.0, 0.0], [1.0, -0.5, 0.3], [-1.5, 1.0, -0.5]):
        twin.move_camera(coords)
        gl = twin.render_images("mount")
        im = render(state, jnp.asarray(coords, jnp.float32))
        seen = gl["segmentation"] >= 0
        assert seen.mean() > 0.5, (name, coords)
        depth_err = np.abs(np.asarray(im.depth) - gl["depth"])[seen].mean()
        agree = np.mean(np.asarray(im.segmentation) == gl["segmentation"])
        print(f"\n{name} {coords}: depth {depth_err:.1e} m, segmentation {agree:.4f}")
        assert depth_err < 1e-3 and agree >= 0.99, (name, coords, depth_err, agree)
    twin.close()


def test_image_gradient_reaches_the_camera_pose(made):
    env = made["needle_threading"]
    state = env.reset(jax.random.PRNGKey(0))

    def loss(coords):
        im = env.render(state, coords, tau=1.0, size=32)
        return jnp.sum(im.rgb * jnp.array([1.0, 0.5, 0.25]))

    g = jax.jit(jax.grad(loss))(jnp.zeros(3, jnp.float32))
    assert np.all(np.isfinite(g)) and np.abs(np.asarray(g)).min() > 0, g


def test_image_actor_sees_proprioception_and_the_mount_image_with_its_target_mask(made):
    # twinrl.learn.imitation's pixel observation: joint angles and velocities, and RGB, depth and
    # the target's mask from the mount; the fixture shows at the default pose, and an image
    # policy (CNN encoder) maps it to an action in [-1, 1].
    from twinrl.learn import imitation
    from twinrl.learn.networks import NetworkConfig, make_network

    env = made["peg_insertion"]
    cfg = imitation.ImitationConfig(observation="pixels", image_size=32)
    observe, spec = imitation.make_observer(env, cfg)
    state = env.reset(jax.random.PRNGKey(0))
    obs = jax.jit(observe)(state, jnp.asarray(env.mount.default, jnp.float32))
    assert spec == {"state": (14,), "camera": (3,), "pixels/mount": (32, 32, 5)}
    assert obs["pixels/mount"].shape == (32, 32, 5)
    np.testing.assert_allclose(obs["camera"], jax.nn.sigmoid(jnp.asarray(env.mount.default)))
    np.testing.assert_array_equal(obs["state"], state.obs[:14])
    mask = np.asarray(obs["pixels/mount"][..., 4])
    assert set(np.unique(mask)) <= {0.0, 1.0} and mask.sum() >= 10, mask.sum()
    depth = np.asarray(obs["pixels/mount"][..., 3])
    assert np.all(depth[mask > 0] > 0.2) and np.all(depth[mask > 0] < 3.0)
    net = make_network(spec, env.action_size, NetworkConfig(hidden=(16,), output="tanh"))
    a = net.apply(net.init(jax.random.PRNGKey(1)), obs)
    assert a.shape == (env.action_size,) and np.all(np.abs(np.asarray(a)) <= 1)
    # the "target" actor reads the image's target cloud, the tool point of its joints and the
    # cloud's mean from the tool instead; by default, not the joints
    cfg = imitation.ImitationConfig(observation="target", image_size=32)
    observe, spec = imitation.make_observer(env, cfg)
    obs = jax.jit(observe)(state, jnp.asarray(env.mount.default, jnp.float32))
    assert spec == {"tool": (3,), "target": (7,), "reach": (3,), "camera": (3,)}
    assert set(obs) == set(spec) and obs["target"][6] > 0  # the target is seen
    np.testing.assert_allclose(obs["tool"], env.tool_point(state.pipeline_state.qpos), atol=1e-6)
    np.testing.assert_allclose(obs["reach"], obs["target"][:3] - obs["tool"], atol=1e-6)
    assert "state" in imitation.make_observer(env, dataclasses.replace(cfg,
                                                                       proprioception=True))[1]


def test_hand_eye_offset_moves_the_real_camera_and_camera_moves_are_counted():
    p = Perturbation(camera_pos_offset=(0.01, -0.02, 0.0), camera_rot_offset=(0.0, 0.03, 0.0))
    twin = RealTwin("peg_insertion", perturbation=p, width=64, height=64)
    ideal = RealTwin("peg_insertion", perturbation=Perturbation.none(), width=64, height=64)
    for t in (twin, ideal):
        t.reset(seed=0)
        assert t.move_camera([1.0, 0.5, 0.0]) > 0
        assert t.camera_steps > 0
    cid = twin.oracle().model.camera("mount").id
    m_true, m_nominal = twin.oracle().model, ideal.oracle().model
    assert np.linalg.norm(m_true.cam_pos[cid] - m_nominal.cam_pos[cid]) == pytest.approx(
        np.linalg.norm([0.01, -0.02, 0.0]), rel=1e-6)
    assert not np.array_equal(twin.render_images("mount")["depth"],
                              ideal.render_images("mount")["depth"])
    nominal = twin.nominal_camera("mount")
    np.testing.assert_allclose(nominal["pos"], m_nominal.cam_pos[cid], atol=1e-6)
    with pytest.raises(ValueError, match="3 finite numbers"):
        twin.move_camera([0.0, np.nan, 0.0])
    with pytest.raises(ValueError, match="has no camera mount"):
        RealTwin("push").move_camera([0.0, 0.0, 0.0])
    twin.close()
    ideal.close()


def test_a_hand_eye_calibration_at_one_pose_puts_the_camera_right_at_every_pose():
    """``CameraMount.with_hand_eye`` of the true camera at the default pose (what the loop's
    calibration fits) gives the mount whose camera is the real one at any other commanded pose;
    an ``envs.make`` with a ``System`` holding that camera builds the task with it."""
    from twinrl.envs.system import System
    from twinrl.render import Camera, quat_to_mat

    p = Perturbation(camera_pos_offset=(0.012, -0.02, 0.03), camera_rot_offset=(0.02, -0.03, 0.01))
    twin = RealTwin("peg_insertion", perturbation=p, width=64, height=64)
    twin.reset(seed=0)
    model = twin.oracle().model
    cid = model.camera("mount").id
    mount = envs.make("peg_insertion").mount

    def true_camera(coords):
        twin.move_camera(coords)
        m = twin.oracle().model
        return np.asarray(m.cam_pos[cid]), np.asarray(m.cam_quat[cid])

    pos, quat = true_camera(np.asarray(mount.default))
    fitted = Camera(pos, quat, np.float64(mount.fovy), 64, 64)
    env = envs.make("peg_insertion", system=System.nominal("peg_insertion").replace(
        cameras={"mount": fitted}))
    np.testing.assert_allclose(env.mount.pos_offset, p.camera_pos_offset, atol=1e-5)
    for coords in ([1.5, -0.7, 0.4], [-2.0, 1.0, -1.0]):
        pos, quat = true_camera(np.asarray(coords))
        cam = env.mount.camera(jnp.asarray(coords, jnp.float32))
        np.testing.assert_allclose(np.asarray(cam.pos), pos, atol=2e-5)
        R = np.asarray(quat_to_mat(jnp.asarray(quat / np.linalg.norm(quat), jnp.float32)))
        np.testing.assert_allclose(np.asarray(cam.xmat), R, atol=2e-5)
        # the nominal mount misses it by the offset
        assert np.linalg.norm(np.asarray(mount.camera(jnp.asarray(coords, jnp.float32)).pos)
                              - pos) > 0.03
    twin.close()


def test_grasp_offset_moves_the_tool_in_the_hand():
    p = Perturbation(tool_pos_offset=(0.003, 0.0, -0.002))
    twin = RealTwin("peg_insertion", perturbation=p)
    ideal = RealTwin("peg_insertion", perturbation=Perturbation.none())
    tool = twin.oracle().model.body("tool").id
    np.testing.assert_allclose(twin.oracle().model.body_pos[tool]
                               - ideal.oracle().model.body_pos[tool], [0.003, 0.0, -0.002])
    # the true tool point is the nominal one without the offset, moved by it (in the tool's
    # frame, rotated into the world's) with it; the robot's own tip observation does not move
    for t in (twin, ideal):
        t.reset(seed=3)
    (tip, R), (tip0, R0) = twin.true_tool(), ideal.true_tool()
    q = jnp.asarray(ideal.oracle().qpos, jnp.float32)
    np.testing.assert_allclose(tip0, np.asarray(envs.make("peg_insertion").tool_point(q)),
                               atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(tip - tip0), np.hypot(0.003, 0.002), atol=1e-5)
    np.testing.assert_allclose(R, R0, atol=1e-6)  # a pure translation of the grasp
    # drawn for the arm tasks, whose spec asks for it
    drawn = Perturbation.sample("peg_insertion", 0)
    assert any(drawn.tool_pos_offset) and any(drawn.tool_rot_offset)
    assert not any(Perturbation.sample("push", 0).tool_pos_offset)


@pytest.mark.parametrize("name", ARM_TASKS)
def test_expert_plan_succeeds_in_sim_and_replays_on_the_unperturbed_twin(name, made):
    """The scripted expert's episode (closed loop in the simulator) succeeds; replayed open loop on
    the real twin without perturbation it ends in the same place through the same contacts (the
    two engines agree), and the task's success metric says so there too."""
    env = made[name]
    step = jax.jit(env.step)
    s = jax.jit(env.reset)(jax.random.PRNGKey(EXPERT_START[name]))
    q0, v0 = np.asarray(s.pipeline_state.qpos), np.asarray(s.pipeline_state.qvel)
    actions = []
    for _ in range(env.episode_length):
        actions.append(env.scripted_action(np.asarray(s.obs)))
        s = step(s, actions[-1])
    q_sim = np.asarray(s.pipeline_state.qpos)
    assert float(env.success(s.pipeline_state.qpos, s.pipeline_state.qvel)) == 1.0, name
    twin = RealTwin(name, perturbation=Perturbation.none())
    twin.reset(options={"qpos": q0, "qvel": v0})
    for a in actions:
        twin.step(a)
    o = twin.oracle()
    tool_gap = np.linalg.norm(np.asarray(env.tool_point(jnp.asarray(o.qpos)))
                              - np.asarray(env.tool_point(jnp.asarray(q_sim))))
    print(f"\n{name}: expert replayed on the unperturbed twin: tool {tool_gap * 1e3:.2f} mm from "
          f"the simulator's, max |dq| {np.abs(o.qpos - q_sim).max():.2e}")
    assert tool_gap < ZERO_TWIN_TOOL_TOL[name], tool_gap
    assert float(env.success(jnp.asarray(o.qpos), jnp.asarray(o.qvel))) == 1.0, name
    twin.close()


def test_approach_plan_heads_the_blade_for_the_pancake_and_solves_nothing(made):
    # trajopt's structured initial guess (bench/manipulation.py restarts): open-loop commands along
    # the line to 1 cm short of the near rim, then still -- the servos lag them, so the blade
    # covers part of the way, along that line, touching nothing, flipping nothing
    env = made["spatula_flipping"]
    step = jax.jit(env.step)
    s = jax.jit(env.reset)(jax.random.PRNGKey(3))
    goal = np.asarray(env.approach_point(s.pipeline_state.qpos))
    start = np.asarray(env.edge(s.pipeline_state.qpos))
    line = (goal - start) / np.linalg.norm(goal - start)
    centre0 = np.asarray(env.pancake(s.pipeline_state.qpos)[0])
    covered = {}
    for short in (0.0, 0.02):
        plan = np.asarray(env.approach_plan(s, short))
        assert plan.shape == (env.episode_length, env.action_size)
        assert np.abs(plan).max() <= 0.9 + 1e-6 and np.all(plan[-10:] == 0)
        np.testing.assert_allclose(plan.sum(0) * env.controller.max_step,
                                   goal - start - short * line, atol=1e-5)
        x = s
        for a in plan:
            x = step(x, a)
        moved = np.asarray(env.edge(x.pipeline_state.qpos)) - start
        covered[short] = float(moved @ line)
        assert np.linalg.norm(moved - covered[short] * line) < 0.2 * covered[short], moved
        np.testing.assert_allclose(env.pancake(x.pipeline_state.qpos)[0], centre0, atol=2e-3)
        assert float(env.success(x.pipeline_state.qpos, x.pipeline_state.qvel)) == 0.0
    print(f"\napproach plan: blade covered {covered[0.0] * 100:.1f} cm of "
          f"{np.linalg.norm(goal - start) * 100:.1f} cm (2 cm short: {covered[0.02] * 100:.1f})")
    assert covered[0.0] > 0.3 * np.linalg.norm(goal - start) and covered[0.02] < covered[0.0]
    with pytest.raises(NotImplementedError, match="approach_point"):
        made["peg_insertion"].approach_plan(made["peg_insertion"].reset(jax.random.PRNGKey(0)))


@pytest.mark.parametrize("name", ARM_TASKS)
def test_state_from_obs_inverts_observe(name, made):
    """Deployment reads the simulator state for camera selection off the robot's observation:
    ``state_from_obs(observe(q, v))`` gives back ``(q, v)`` -- for the spatula with a tilted,
    sliding pancake (its spin about its own axis, which the observation does not carry, is zero
    here, as is its angular velocity)."""
    env = made[name]
    q, v = (np.asarray(x, np.float64) for x in env.initial_state(jax.random.PRNGKey(4)))
    rng = np.random.default_rng(0)
    v[:7] = rng.normal(0.0, 0.3, 7)
    if name == "spatula_flipping":
        tilt = 0.7  # about the y axis, towards the rail: the smallest turn from flat to 'up'
        q[12:16] = [np.cos(tilt / 2), 0.0, np.sin(tilt / 2), 0.0]
        v[9:12] = [0.1, -0.05, 0.2]
    obs = env.observe(jnp.asarray(q), jnp.asarray(v))
    q2, v2 = env.state_from_obs(obs)
    np.testing.assert_allclose(np.asarray(q2), q, atol=2e-6)
    np.testing.assert_allclose(np.asarray(v2), v, atol=2e-6)
    np.testing.assert_allclose(np.asarray(env.observe(q2, v2)), np.asarray(obs), atol=2e-6)
    # batched, as sysid's windows, the hybrid model and the residual's start states call it: a
    # (2, 3, obs) batch gives each row's own state (the row-sliced bug read rows as features)
    q_other = np.asarray(env.initial_state(jax.random.PRNGKey(5))[0], np.float64)
    q_b, v_b = np.stack([q, q_other]), np.stack([v, np.zeros_like(v)])
    obs_b = np.stack([np.asarray(env.observe(jnp.asarray(a), jnp.asarray(b)))
                      for a, b in zip(q_b, v_b)])
    obs_b = np.stack([obs_b] * 3, axis=1)
    qb, vb = env.state_from_obs(obs_b)
    assert qb.shape == (2, 3, env.sim.nq) and vb.shape == (2, 3, env.sim.nv)
    assert not np.allclose(np.asarray(qb[0, 0]), np.asarray(qb[1, 0]))
    for i in range(2):
        q1, v1 = env.state_from_obs(obs_b[i, 0])
        for j in range(3):
            np.testing.assert_allclose(np.asarray(qb[i, j]), np.asarray(q1), atol=1e-6)
            np.testing.assert_allclose(np.asarray(vb[i, j]), np.asarray(v1), atol=1e-6)


def test_sysid_windows_start_at_the_recorded_arm_states(made):
    """The arm loop's sysid (``ArmLoopConfig.sysid``) cuts the recorded episodes into shooting
    windows, each starting at the state read off its first observation: on the needle, two
    episodes of 10 steps, windows of 5 -> four windows at the states recorded at steps 0 and 5."""
    from twinrl.real2sim import sysid

    env = made["needle_threading"]
    states = [env.initial_state(jax.random.PRNGKey(k)) for k in range(20)]
    obs = np.stack([np.asarray(env.observe(q, v)) for q, v in states]).reshape(2, 10, -1)
    act = np.zeros((2, 10, env.action_size), np.float32)
    w = sysid.windows_from_dataset(env, {"obs": obs, "action": act, "next_obs": obs}, 5,
                                   max_latency=1)
    assert w.qpos0.shape == (4, env.sim.nq) and w.actions.shape == (4, 6, env.action_size)
    for i, k in enumerate((0, 5, 10, 15)):
        np.testing.assert_allclose(w.qpos0[i], np.asarray(states[k][0]), atol=2e-6)


@pytest.mark.parametrize("name", ARM_TASKS)
def test_real_success_is_judged_at_the_true_tool(name, made):
    """``RealTwin.success`` judges at the tool the real engine carries. The scripted expert's
    episode on the unperturbed twin succeeds by both the nominal kinematics and the twin; put the
    same joint angles into a twin whose grasp is 2 cm off, and the nominal kinematics (the
    robot's belief) still say "done" while the true peg tip / thread is 2 cm away: the twin says
    so. (The spatula's success is the pancake's alone: both agree.)"""
    env = made[name]
    judge = lambda o: float(env.success(jnp.asarray(o.qpos, jnp.float32),  # noqa: E731
                                        jnp.asarray(o.qvel, jnp.float32)))
    twin = RealTwin(name, perturbation=Perturbation.none())
    obs, _ = twin.reset(seed=EXPERT_START[name])
    for _ in range(env.episode_length):
        obs, *_ = twin.step(env.scripted_action(obs))
    done = twin.oracle()
    assert (judge(done), twin.success()) == (1.0, 1.0)
    twin.close()
    off = RealTwin(name, perturbation=Perturbation(tool_pos_offset=(0.0, 0.02, 0.0)))
    off.reset(options={"qpos": done.qpos, "qvel": done.qvel})
    expected = 1.0 if name == "spatula_flipping" else 0.0
    assert (judge(off.oracle()), off.success()) == (1.0, expected)
    off.close()


def test_target_cloud_finds_the_hole_from_anywhere_it_is_seen(made):
    """The image actor's ``"target"`` key: the peg fixture's back-projected depth pixels centre
    within 3 cm of the hole (the wall faces turned to the camera pull the centre towards it:
    2.5 cm from the default pose) from the default pose and from three others, and the count
    says how much of it shows."""
    env = made["peg_insertion"]
    state = env.reset(jax.random.PRNGKey(3))
    hole = np.asarray(env.tip_and_hole(state.pipeline_state.qpos)[1])
    observe = jax.jit(lambda c: env.image_observation(state, c, size=32)["target"])
    for coords in (env.mount.default, (1.0, 0.5, -0.5), (-1.2, -0.8, 0.4), (0.3, 1.2, 1.0)):
        t = np.asarray(observe(jnp.asarray(coords, jnp.float32)))
        assert t[6] > np.log1p(5), (coords, t)
        assert np.linalg.norm(t[:2] - hole[:2]) < 0.03, (coords, t[:3], hole)
        assert np.all(t[3:6] > 1e-3) and np.all(t[3:6] < 0.05)


def test_target_pose_is_fitted_to_one_depth_image(made):
    """``fit_target_pose`` (peg): from random mount poses where the fixture shows, the fixture at
    the fitted pose sits within millimetres of where it is (median), where the target cloud's
    mean is centimetres off (the faces a pose shows); ``"estimate"`` is the privileged
    observation of that state. (The needle's eye, seen only from near its axis, takes minutes of
    random poses to see 12 times: measured apart, 0.9 mm median against the mean's 2.3 mm.)"""
    name = "peg_insertion"
    env = made[name]
    model = env.sim.mj_model
    d = mujoco.MjData(model)

    def target_centre(qpos):
        d.qpos[:] = qpos
        mujoco.mj_kinematics(model, d)
        return d.geom_xpos[env.target_geom_ids].mean(0)

    obs_of = jax.jit(lambda s, c: env.image_observation(s, c))
    rng = np.random.default_rng(1)
    fit_err, mean_err, rms = [], [], []
    for k in range(4):
        s = env.reset(jax.random.PRNGKey(k))
        q = np.asarray(s.pipeline_state.qpos, np.float64)
        true = target_centre(q)
        seen = 0
        while seen < 3:
            u = rng.uniform(0.1, 0.9, 3)
            o = obs_of(s, jnp.asarray(np.log(u / (1 - u)), jnp.float32))
            if float(o["target"][6]) < np.log1p(20):  # fewer than 20 target pixels
                continue
            seen += 1
            q_hat = np.asarray(env.estimated_state(jnp.asarray(s.obs[:14]), o["pose"])[0])
            fit_err.append(np.linalg.norm(target_centre(q_hat) - true))
            mean_err.append(np.linalg.norm(np.asarray(o["target"])[:3] - true))
            # the hole's entries of the privileged observation
            np.testing.assert_allclose(np.asarray(o["estimate"])[14:], np.asarray(s.obs)[14:],
                                       atol=3e-3)
            # ... which is what perfect perception gives (the residual's training input)
            np.testing.assert_allclose(np.asarray(o["estimate"]),
                                       np.asarray(env.estimate_from_obs(s.obs)), atol=3e-3)
            # what the fit stands on: the pixels it used, and a residual of a fraction of a mm
            np.testing.assert_allclose(o["support"][0], o["target"][6], rtol=1e-5)
            rms.append(float(o["support"][1]))
    assert np.median(rms) < 1.0 and np.all(np.asarray(rms) >= 0), rms
    assert np.median(fit_err) < 0.003, fit_err
    assert np.median(fit_err) < np.median(mean_err) / 3, (fit_err, mean_err)


def test_target_pose_fit_uses_a_subset_of_many_target_pixels(made):
    """An image showing more target pixels than ``fit_target_pose`` uses (``points``) is fitted
    from the subset as well as from all: the first guess is the subset's mean (it had divided
    the subset's sum by every pixel's count, pulling the guess toward the camera; at 256x256,
    where the needle shows more than the default 256 points, half its views fitted wrong).
    A needle view at 128x128 showing ~70 pixels, fitted from 16 and from all."""
    from twinrl.learn.imitation import ImitationConfig, episode_coords

    env = made["needle_threading"]
    s = env.reset(jax.random.PRNGKey(1))
    coords = episode_coords(env, ImitationConfig(), jax.random.PRNGKey(2))
    img = env.render(s, coords, size=128)
    mask = jnp.sum(img.weights[..., env._target_columns], axis=-1)
    assert float(jnp.sum(mask)) > 48, float(jnp.sum(mask))  # three times the points used
    cam = env.mount.camera(coords, 128, 128)
    idx = np.asarray(env.target_joints)
    truth = np.asarray(env._wrap_target_pose(s.pipeline_state.qpos[idx]))
    for points in (16, 256):
        pose = jax.jit(lambda j, d, m: env.fit_target_pose(j, cam, d, m, points=points))(
            s.obs[:14], img.depth, mask)
        err = np.abs(np.asarray(env._wrap_target_pose(pose - truth)))
        assert np.max(err) < 0.002, (points, err)


def test_the_pose_fits_hinge_grid_finds_a_heading_the_local_restarts_miss(made):
    """``fit_target_pose(hinge_grid=K)`` (``ArmConfig.pose_hinge_grid``): a needle view (found
    by ``bench/pose_views.py`` (in git history)'s draw) where the local restarts stop 0.16 rad off the eye's
    heading at a 0.5 mm RMS residual; the hinge grid's starts reach the exact fit (heading to
    1e-3 rad, a residual under 0.01 mm)."""
    from twinrl.learn.imitation import ImitationConfig, episode_coords

    env = made["needle_threading"]
    k_cam, k_reset = jax.random.split(jax.random.split(jax.random.PRNGKey(1), 40)[12])
    s = env.reset(k_reset)
    coords = episode_coords(env, ImitationConfig(observation="pose"), k_cam)
    img = env.render(s, coords, size=64)  # the view was found at 64x64
    mask = jnp.sum(img.weights[..., env._target_columns], axis=-1)
    cam = env.mount.camera(coords, 64, 64)
    idx = np.asarray(env.target_joints)
    truth = np.asarray(env._wrap_target_pose(s.pipeline_state.qpos[idx]))
    out = {}
    for grid in (0, 8):
        pose, rms = jax.jit(lambda j, d, m: env.fit_target_pose(
            j, cam, d, m, with_residual=True, hinge_grid=grid))(s.obs[:14], img.depth, mask)
        err = np.abs(np.asarray(env._wrap_target_pose(pose - truth)))  # the eye's half turn
        out[grid] = err, float(rms) * 1e3
    assert out[0][0][3] > 0.1 and out[0][1] > 0.1, out  # the local fit: the wrong heading
    assert out[8][0][3] < 1e-3 and np.max(out[8][0][:3]) < 0.003 and out[8][1] < 0.01, out


def test_target_pose_fit_has_the_converged_fits_derivative(made):
    """The camera ascent differentiates ``fit_target_pose`` through the renderer: its derivative
    must be the converged fit's. Moving the camera by d with the depth image and mask held moves
    the back-projected cloud by d, so peg's fitted fixture slides (world x and y) follow d
    exactly; through the soft image (tau 1, the ascent's), reverse mode agrees with central
    differences of the fit in the mount's coordinates. (Before: NaN there -- the Huber
    residual's unused square root -- and ~1e12 through the needle's unrolled iterations; the
    Gauss-Newton J'J in place of the full Hessian was 30-40 % off.)"""
    env = made["peg_insertion"]
    state = env.reset(jax.random.PRNGKey(3))
    # a pose that shows the fixture's x- and y-facing walls (from the default pose, 38 pixels
    # of mostly x-facing wall leave its y barely determined)
    coords = jnp.asarray([1.0, 0.5, -0.5], jnp.float32)
    img = env.render(state, coords, size=32)
    mask = jnp.sum(img.weights[..., env._target_columns], axis=-1)
    cam = env.mount.camera(coords, 32, 32)

    def fit(d):  # the camera moved by d (m, world), the image held
        return env.fit_target_pose(state.obs[:14], cam.translated(d), img.depth, mask)

    jac = np.asarray(jax.jit(jax.jacfwd(fit))(jnp.zeros(3)))
    np.testing.assert_allclose(jac, [[1, 0, 0], [0, 1, 0]], atol=2e-3)

    def soft(c):
        return env.image_observation(state, c, size=32, tau=1.0, keys=("pose",))["pose"]

    rev = np.asarray(jax.jit(jax.jacrev(soft))(coords))
    assert np.all(np.isfinite(rev)), rev
    pose = jax.jit(soft)
    h = 3e-3
    fd = np.stack([(np.asarray(pose(coords + h * e)) - np.asarray(pose(coords - h * e))) / (2 * h)
                   for e in jnp.eye(3)], axis=1)
    np.testing.assert_allclose(rev, fd, atol=0.1 * np.abs(fd).max())


def test_calibration_poses_start_at_the_default_and_spread_over_the_workspace():
    """``CameraMount.calibration_poses``: the loop's round-0 mount poses (its hand-eye
    calibration needs the scene from several of them) -- the default pose first, distinct
    poses inside the workspace, the same every call."""
    mount = envs.make("needle_threading").mount
    poses = mount.calibration_poses(5)
    assert poses.shape == (5, 3)
    np.testing.assert_array_equal(poses[0], mount.default)
    np.testing.assert_array_equal(poses, mount.calibration_poses(5))
    np.testing.assert_array_equal(poses[:3], mount.calibration_poses(3))
    sph = np.array([np.asarray(mount.spherical(jnp.asarray(c, jnp.float32))) for c in poses])
    lo, hi = mount._ranges().T
    assert np.all(sph > lo) and np.all(sph < hi)
    gaps = np.linalg.norm((sph[:, None] - sph[None]) / (hi - lo), axis=-1)
    assert gaps[~np.eye(5, dtype=bool)].min() > 0.1, gaps
    with pytest.raises(ValueError, match="n must be >= 1"):
        mount.calibration_poses(0)


def test_tool_geoms_are_the_tools_and_nothing_else():
    """``handeye.tool_geoms``: what the hand-eye calibration leaves out (the tool, whose grasp
    in the hand is not known) -- every geom of body ``tool`` and below it, no arm or scene
    geom."""
    from twinrl.real2sim.handeye import tool_geoms

    for task, names in (("needle_threading", {"thread"}), ("peg_insertion", {"peg"}),
                        ("spatula_flipping", {"handle", "blade", "blade0", "blade1", "blade2"})):
        m = envs.make(task).sim.mj_model
        assert {m.geom(g).name for g in tool_geoms(m)} == names, task


def test_set_grasp_moves_the_tool_as_the_real_twins_perturbation_does():
    # The identified grasp (System.tool) moves the simulator's tool body exactly as
    # the real twin's hidden Perturbation moves its own, and tool_pose (reward, success, the
    # image observation's "tool") is the controller's tool centre point carried by that body.
    import copy

    from twinrl.envs.system import System

    pos, rot = np.array([0.004, -0.003, 0.006]), np.array([0.03, -0.02, 0.05])
    system = System.nominal("needle_threading").replace(
        objects={"tool": {"pos_offset": pos, "rot_offset": rot}})
    env = envs.make("needle_threading", system=System.from_json(system.to_json()))
    nominal = envs.make("needle_threading")
    real = copy.deepcopy(nominal.sim.mj_model)
    Perturbation(tool_pos_offset=tuple(pos), tool_rot_offset=tuple(rot)).apply(real)
    m = env.sim.mj_model
    t = m.body("tool").id
    np.testing.assert_allclose(m.body_pos[t], real.body_pos[t], atol=1e-12)
    np.testing.assert_allclose(m.body_quat[t], real.body_quat[t], atol=1e-9)
    q = np.zeros(m.nq)
    q[:7] = np.asarray(nominal._q_start)
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    tip, R = env.tool_pose(jnp.asarray(q))
    Rt = d.xmat[t].reshape(3, 3)
    np.testing.assert_allclose(np.asarray(tip), d.xpos[t] + Rt @ np.asarray(env.controller.tcp),
                               atol=1e-6)
    np.testing.assert_allclose(np.asarray(R), Rt, atol=1e-6)
    # the nominal task's tip is 7 mm away, and its thread is where the grasp puts it
    far = np.linalg.norm(np.asarray(nominal.tool_point(jnp.asarray(q))) - np.asarray(tip))
    assert far > 5e-3
    np.testing.assert_allclose(np.asarray(env.thread(jnp.asarray(q))[0]), np.asarray(tip))
    # what the robot reports (the real twin's observation) stays its nominal kinematics'
    qj, vj = jnp.asarray(q), jnp.zeros(m.nv)
    np.testing.assert_array_equal(np.asarray(env.observe(qj, vj)),
                                  np.asarray(nominal.observe(qj, vj)))
    # ... while the image actor's pose estimate reads the thread where the twin believes it is:
    # from that report, the tip at the identified grasp (an actor trained on one and deployed on
    # the other reads the thread 7 mm off)
    est = np.asarray(env.estimate_from_obs(env.observe(qj, vj)))
    np.testing.assert_allclose(est[14:17], np.asarray(tip), atol=1e-5)
    np.testing.assert_allclose(est, np.asarray(env.observe(qj, vj, nominal=False)), atol=1e-5)
    with pytest.raises(ValueError, match="non-finite grasp"):
        env.set_grasp((np.nan, 0, 0), (0, 0, 0))


def test_grasp_errors_score_the_hidden_grasp_zero_and_the_nominal_at_its_size():
    # evaluation only: the twin's own hidden grasp scores 0; the nominal one scores the tool
    # centre point's displacement by that grasp; a grasp 2 mm off along x scores 2 mm
    from twinrl.eval import grasp_errors

    p = Perturbation(tool_pos_offset=(0.003, -0.002, 0.004), tool_rot_offset=(0.02, 0.0, 0.1))
    exact = grasp_errors("needle_threading", 0, p.tool_pos_offset, p.tool_rot_offset,
                         perturbation=p)
    assert exact["grasp_tcp_err_mm"] < 1e-9 and exact["grasp_rot_err_deg"] < 1e-6
    tcp = np.array([0.0, 0.0, 0.12])
    R = np.empty(9)
    mujoco.mju_quat2Mat(R, np.array([np.cos(0.051), 0.02 * np.sin(0.051) / 0.102, 0.0,
                                     0.1 * np.sin(0.051) / 0.102]))
    moved = np.asarray(p.tool_pos_offset) + R.reshape(3, 3) @ tcp - tcp
    assert exact["nominal_tcp_err_mm"] == pytest.approx(np.linalg.norm(moved) * 1e3, rel=1e-3)
    off = grasp_errors("needle_threading", 0, np.asarray(p.tool_pos_offset) + [0.002, 0, 0],
                       p.tool_rot_offset, perturbation=p)
    assert off["grasp_tcp_err_mm"] == pytest.approx(2.0, abs=1e-6)


def _lift(twin, steps: int = 5) -> np.ndarray:
    """The blade's displacement (m) after ``steps`` half-speed lift commands from reset key 0."""
    env = twin.task
    twin.reset(seed=0)
    p0 = np.asarray(env.tool_point(jnp.asarray(twin.oracle().qpos), nominal=True))
    for _ in range(steps):
        twin.step(np.array([0.0, 0.0, 0.5], np.float32))
    return np.asarray(env.tool_point(jnp.asarray(twin.oracle().qpos), nominal=True)) - p0


def test_the_controller_calibrated_to_the_servos_moves_the_tool_as_commanded():
    """Servos 20-30 % off their nominal speed (gain over damping) bend a commanded lift; the
    controller calibrated with their speeds (``ArmTask.servo_speed``) lifts as the nominal arm
    does. (Spatula, MuJoCo C; the real twin's controller is the task's, as configured.)"""
    nominal = RealTwin("spatula_flipping", perturbation=Perturbation.none())
    slow = Perturbation(gain_scale=(1.0, 0.85, 1.0, 1.2, 1.0, 1.0, 0.8),
                        damping_scale=(1.0, 1.0, 1.2) + (1.0,) * 12)
    twin = RealTwin("spatula_flipping", perturbation=slow)
    want = _lift(nominal)

    def angle(u):
        return np.degrees(np.arccos(np.dot(u, want) / np.linalg.norm(u) / np.linalg.norm(want)))

    bent = _lift(twin)
    speed = twin.task.servo_speed(twin.oracle().params)  # the truth: evaluation only
    np.testing.assert_allclose(speed, [1, 0.85, 1 / 1.2, 1.2, 1, 1, 0.8], rtol=1e-5)
    twin.calibrate_controller(speed)
    assert twin.joint_speed == tuple(speed)
    fixed = _lift(twin)
    print(f"\nlift {1e3 * np.linalg.norm(want):.1f} mm; servos off: {angle(bent):.1f} deg, "
          f"{np.linalg.norm(bent) / np.linalg.norm(want):.2f} as far; calibrated: "
          f"{angle(fixed):.1f} deg, {np.linalg.norm(fixed) / np.linalg.norm(want):.2f}")
    assert angle(bent) > 10.0 and angle(fixed) < 0.4 * angle(bent), (angle(bent), angle(fixed))
    assert abs(np.linalg.norm(fixed) / np.linalg.norm(want) - 1.0) < 0.15
    twin.calibrate_controller(None)  # back to the nominal controller: bent again
    np.testing.assert_allclose(_lift(twin), bent, atol=1e-9)
    with pytest.raises(ValueError, match="joint_speed must be 7 positive"):
        twin.calibrate_controller([1.0, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="no Cartesian controller"):
        RealTwin("pendulum_swingup").calibrate_controller(np.ones(7))
    nominal.close()
    twin.close()


def test_servo_speed_errors_score_the_calibration_against_the_hidden_servos():
    from twinrl import eval as evaluation
    from twinrl.envs.system import System

    env = envs.make("spatula_flipping")
    slow = Perturbation(gain_scale=(1.0, 0.8) + (1.0,) * 5)
    truth = RealTwin("spatula_flipping", perturbation=slow).oracle().params
    exact = evaluation.servo_speed_errors(env, truth, "spatula_flipping", 0, slow)
    assert sorted(exact) == [f"joint{i}" for i in range(1, 8)] and max(exact.values()) < 1e-9
    nominal = evaluation.servo_speed_errors(env, System.nominal("spatula_flipping").params,
                                            "spatula_flipping", 0, slow)
    assert nominal["joint2"] == pytest.approx(0.25) and nominal["joint1"] < 1e-9


def test_a_systems_controller_calibration_configures_the_task(tmp_path):
    from twinrl.envs.system import System

    speed = np.array([1.0, 0.9, 1.1, 1.3, 1.0, 0.95, 0.8])
    system = System.nominal("spatula_flipping").replace(
        objects={"controller": {"joint_speed": speed}})
    system.save(tmp_path / "system.json")
    env = envs.make("spatula_flipping", system=System.load(tmp_path / "system.json"))
    assert env.controller.joint_speed == tuple(speed)
    assert envs.make("spatula_flipping").controller.joint_speed is None  # the class's untouched
    q = jnp.asarray(env._q_start, jnp.float32)
    a = jnp.array([0.3, -0.2, 0.5], jnp.float32)
    step = env.controller(q, a) - q
    plain = envs.make("spatula_flipping").controller(q, a) - q
    np.testing.assert_allclose(step * speed, plain, rtol=1e-4, atol=1e-7)


def test_with_system_builds_a_new_task_from_the_system_alone():
    """``ArmTask.with_system``: a copy as the system describes it (the tool's grasp, the
    controller's calibration, the mount's hand-eye offset), the task it is called on untouched;
    what the system leaves out is the task's nominal one, so ``with_system(system.replace(
    controller=None))`` is the twin with the nominal controller. The ``sys`` setter still applies
    a system in place."""
    from twinrl.envs.system import System

    nominal = System.nominal("peg_insertion")
    speed = np.array([1.0, 0.9, 1.1, 1.3, 1.0, 0.95, 0.8])
    system = nominal.replace(objects={
        "tool": {"pos_offset": np.array([0.004, -0.003, 0.003]),
                 "rot_offset": np.array([-0.05, 0.06, 0.0])},
        "controller": {"joint_speed": speed}})
    task = envs.make("peg_insertion")
    calibrated = task.with_system(system)
    assert task.sys is None and task.grasp is None and task.controller.joint_speed is None
    assert calibrated.sys is system and calibrated.controller.joint_speed == tuple(speed)
    q = jnp.asarray(np.r_[task._q_start, np.zeros(task.sim.nq - 7)], jnp.float32)
    moved = np.linalg.norm(np.asarray(calibrated.tool_point(q) - task.tool_point(q)))
    assert calibrated.grasp is not None and moved > 1e-3
    plain = calibrated.with_system(system.replace(controller=None))
    assert plain.controller.joint_speed is None and calibrated.controller.joint_speed is not None
    assert plain.sim is calibrated.sim  # the same grasp: the simulator is not rebuilt
    back = calibrated.with_system(nominal)
    assert back.grasp is None and back.controller.joint_speed is None
    np.testing.assert_array_equal(np.asarray(back.tool_point(q)), np.asarray(task.tool_point(q)))
    camera = task.mount.camera(jnp.asarray([0.3, -0.2, 0.1]))
    mounted = task.with_system(nominal.replace(cameras={"mount": camera}))
    assert any(mounted.mount.pos_offset) and task.mount == type(task).mount
    assert mounted.with_system(nominal).mount == type(task).mount
    legacy = envs.make("peg_insertion")
    legacy.sys = system
    assert legacy.grasp is not None and legacy.controller.joint_speed == tuple(speed)
