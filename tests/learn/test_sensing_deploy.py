"""Deployment with active sensing on a real twin (``twinrl.sim2real.active``), short peg
insertion: the real mount image is the simulator's view of the read state, the deployer moves
the camera to Q's choice and counts the moves, and a state expert deploys as ``oracle``.

Apart from ``test_sensing.py`` so that the two files run on both test workers. The Q here is
untrained: what is checked is the deployment's mechanics (Q's choice never below the default
pose's Q by the hard image, camera steps counted), which any Q must get right.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs
from twinrl.learn import sensing
from twinrl.learn.networks import Network, NetworkConfig

from tests.learn._peg import PIX, T


@pytest.fixture(scope="module")
def trained(peg):
    """A sensing Q of the actor, initialised at random (its fit is ``test_sensing.py``'s)."""
    env, actor, _ = peg
    cfg = sensing.SensingConfig(hidden=(32,), restarts=2, ascent_steps=3)
    q = sensing.make_q(actor, env.action_size, cfg)
    return cfg, q, q.init(jax.random.PRNGKey(7)), None, None


@pytest.fixture(scope="module")
def twin():
    from twinrl.real.perturbation import Perturbation
    from twinrl.real.twin import RealTwin

    t = RealTwin("peg_insertion", perturbation=Perturbation.none(), width=PIX, height=PIX,
                 config={"episode_length": T})
    yield t
    t.close()


def test_real_image_observation_is_the_simulators_view_of_the_read_state(peg, twin):
    """What the image actor sees on the (unperturbed) real twin -- OpenGL RGB, depth and the
    segmentation's target mask -- is what the simulator renders of the state read off the twin's
    observation (``state_from_obs``), at an arbitrary mount pose."""
    from twinrl.sim2real import active

    env, _, _ = peg
    obs, _ = twin.reset(seed=2)
    coords = np.array([0.8, -0.5, 0.3])
    twin.move_camera(coords)
    real = active.real_image_observation(twin, env, obs, PIX)
    sim = jax.jit(lambda o, c: env.image_observation(active.sim_state(env, o), c, size=PIX))(
        jnp.asarray(obs), jnp.asarray(coords, jnp.float32))
    np.testing.assert_allclose(real["state"], np.asarray(sim["state"]), atol=1e-6)
    r, s = real["pixels/mount"], np.asarray(sim["pixels/mount"])
    assert np.mean(np.abs(r[..., 3] - s[..., 3])) < 1e-3  # depth, m
    assert np.mean(r[..., 4] == s[..., 4]) >= 0.97 and r[..., 4].sum() >= 3  # the target's mask
    assert np.mean(np.abs(r[..., :3] - s[..., :3])) < 0.1  # RGB: shading differs (measured 0.06)
    # the target cloud (mean, spread, log count) from the commanded pose: the same numbers
    np.testing.assert_allclose(real["target"][:6], np.asarray(sim["target"])[:6], atol=2e-3)
    assert abs(real["target"][6] - float(sim["target"][6])) < 0.15
    with pytest.raises(ValueError, match="renders 16x16; the actor needs 32x32"):
        active.real_image_observation(twin, env, obs, 32)


def test_deployment_moves_the_camera_to_qs_choice_and_counts_the_moves(peg, trained, twin):
    from twinrl.learn.camera_choice import q_value
    from twinrl.sim2real import active

    env, actor, actor_params = peg
    cfg, q, q_params, _, _ = trained
    dep = active.Deployer(env, actor, actor_params, q=q, q_params=q_params, sensing=cfg)
    twin.move_camera(env.mount.default)
    res = dep.run(twin, active.DeployConfig(camera="selected", episodes=2, reselect_every=4),
                  seed=5)
    assert res["steps"] == [T, T] and res["choices"] == [2, 2]
    assert len(res["success"]) == 2 and set(res["success"]) <= {0.0, 1.0}
    first = np.asarray(res["coords"][0])
    # the first choice is Q's best by its hard image, never below the default pose's Q
    obs, _ = twin.reset(seed=5)

    @jax.jit  # one compile, not the renderer's and the networks' operations one by one
    def q_of(c):
        hard = env.image_observation(active.sim_state(env, jnp.asarray(obs)), c, size=PIX)
        return q_value(q, q_params, hard, actor.apply(actor_params, hard))

    value = lambda c: float(q_of(jnp.asarray(c, jnp.float32)))  # noqa: E731
    assert value(first) >= value(env.mount.default) - 1e-5
    assert res["camera_steps"][0] >= env.mount.steps_to_move(env.mount.default, first)
    # the fixed camera never moves; a random one moves as far as the mount says
    twin.move_camera(env.mount.default)
    fixed = dep.run(twin, active.DeployConfig(camera="default", episodes=2))
    assert fixed["camera_steps"] == [0, 0] and fixed["choices"] == [1, 1]
    rand = dep.run(twin, active.DeployConfig(camera="random", episodes=2), seed=1)
    a, b = (np.asarray(c) for c in rand["coords"])
    assert rand["camera_steps"][1] == env.mount.steps_to_move(a, b) and not np.allclose(a, b)
    with pytest.raises(ValueError, match="needs the sensing-aware Q"):
        active.Deployer(env, actor, actor_params).run(twin, active.DeployConfig(episodes=1))
    with pytest.raises(ValueError, match="deploys a state policy"):
        dep.run(twin, active.DeployConfig(camera="oracle", episodes=1))
    with pytest.raises(ValueError, match="camera must be one of"):
        active.DeployConfig(camera="best")


def test_oracle_deployment_of_a_state_expert_succeeds_on_the_real_twin():
    """``camera="oracle"``: a state policy on the twin's observation; the scripted peg expert
    (in JAX) inserts the peg on the unperturbed twin, and the deployment says so."""
    from twinrl.real.perturbation import Perturbation
    from twinrl.real.twin import RealTwin
    from twinrl.sim2real import active

    env = envs.make("peg_insertion")
    step = env.controller.max_step

    def expert(_, obs):
        d = obs[20:23]
        lateral = jnp.hypot(d[0], d[1]) < 0.004
        a = jnp.concatenate([-d[:2] / step, jnp.where(lateral, -1.0, (0.08 - d[2]) / step)[None]])
        return jnp.clip(a, -1.0, 1.0)

    policy = Network(init=lambda k: {}, apply=expert, in_size=env.observation_size, out_size=3,
                     config=NetworkConfig(), obs_spec=env.observation_size)
    real = RealTwin("peg_insertion", perturbation=Perturbation.none())
    res = active.deploy(env, real, policy, {}, active.DeployConfig(camera="oracle", episodes=2))
    assert res["success"] == [1.0, 1.0] and res["camera_steps"] == [0, 0]
    assert res["steps"] == [env.episode_length] * 2 and res["choices"] == [0, 0]

    # a residual sees the measured observation and the actor's action, and its correction is
    # what is sent: one that cancels the expert leaves the peg where it started
    seen = []

    def cancel(obs, a):
        seen.append((np.array(obs), np.array(a)))
        return -a

    res = active.deploy(env, real, policy, {}, active.DeployConfig(camera="oracle", episodes=1),
                        residual=cancel)
    assert real.joint_speed is None
    # the deployment configures the real arm's controller as its task's is calibrated
    calibrated = envs.make("peg_insertion")
    calibrated.calibrate_controller([1.0, 0.9, 1.1, 1.2, 1.0, 1.0, 0.8])
    active.deploy(calibrated, real, policy, {}, active.DeployConfig(camera="oracle", episodes=1))
    assert real.joint_speed == (1.0, 0.9, 1.1, 1.2, 1.0, 1.0, 0.8)
    active.deploy(env, real, policy, {}, active.DeployConfig(camera="oracle", episodes=1))
    assert real.joint_speed is None
    real.close()
    assert res["success"] == [0.0] and len(seen) == env.episode_length
    for obs, a in seen[:3]:
        np.testing.assert_allclose(a, np.asarray(expert(None, jnp.asarray(obs))), atol=1e-6)


def test_pose_memory_acts_on_the_best_supported_frames_fit(monkeypatch):
    """``DeployConfig.pose_memory="best"``: a pose actor acts on the target fit of the frame with
    the most target pixels so far (the latest on a tie), its estimate rebuilt from each step's
    joints; ``"none"`` on each frame's own fit. The frames' fits are scripted here (the fit
    itself is ``tests/envs``'), so what is checked is which one the deployer hands the actor."""
    from twinrl.learn.networks import Network
    from twinrl.real.perturbation import Perturbation
    from twinrl.real.twin import RealTwin
    from twinrl.sim2real import active

    env = envs.make("peg_insertion", episode_length=T, image_size=PIX)
    P = len(env.target_joints)
    fits = [(np.full(P, 0.01 * k, np.float32), pix) for k, pix in
            enumerate([3.0, 5.0, 4.0, 5.0, 2.0, 6.0])]  # (pose, target pixels) per frame
    estimate = jax.jit(env.pose_estimate)
    frame = iter(range(10 ** 6))

    def observation(twin, env, obs, size, img=None, keys=None):
        pose, pixels = fits[next(frame) % T]
        return {"pose": pose, "support": np.array([pixels, 0.1], np.float32),
                "estimate": np.asarray(estimate(jnp.asarray(obs[:14]), jnp.asarray(pose)))}

    monkeypatch.setattr(active, "real_image_observation", observation)
    seen = []
    actor = Network(lambda k: {}, lambda p, o: jnp.zeros(env.action_size), env.observation_size,
                    env.action_size, NetworkConfig(), {"estimate": (env.observation_size,)})
    with RealTwin("peg_insertion", perturbation=Perturbation.none(), width=PIX, height=PIX,
                  config={"episode_length": T}) as twin:
        step, observed = twin.step, []

        def recording_step(a):
            out = step(a)
            observed.append(out[0])
            return out

        def act(params, o):
            seen.append(np.asarray(o["estimate"]))
            return np.zeros(env.action_size, np.float32)

        twin.step = recording_step
        for memory, kept in (("best", [0, 1, 1, 3, 3, 5]), ("none", [0, 1, 2, 3, 4, 5])):
            dep = active.Deployer(env, actor, {})
            dep._act = act
            seen.clear()
            observed.clear()
            frame = iter(range(10 ** 6))
            dep.run(twin, active.DeployConfig(camera="default", episodes=1,
                                              pose_memory=memory))
            obs0, _ = twin.reset(seed=0)  # the episode's first observation again
            joints = [obs0[:14]] + [o[:14] for o in observed[:-1]]
            assert len(seen) == T
            for t, k in enumerate(kept):
                np.testing.assert_allclose(seen[t], np.asarray(estimate(
                    jnp.asarray(joints[t], jnp.float32), jnp.asarray(fits[k][0]))), atol=1e-6,
                    err_msg=f"{memory}: step {t} should act on frame {k}'s fit")


def test_the_camera_check_plays_each_start_with_qs_choice_and_the_default(peg, trained):
    """``check_choice``: per start, Q's choice is ``select_camera``'s from that start, both
    columns are the actor's episodes from the same starts (``view_outcomes``), and the choice
    "pays" only if it succeeds on more of them than the default camera."""
    from twinrl.learn.camera_choice import CameraCheck, check_choice, select_camera, view_outcomes

    env, actor, actor_params = peg
    cfg, q, q_params, _, _ = trained
    keys = jax.random.split(jax.random.PRNGKey(3), 3)
    seen = []
    chk = check_choice(env, q, q_params, actor, actor_params, cfg, keys, on_choice=seen.append)
    assert seen == [0, 1, 2] and chk.coords.shape == (3, 3)
    k = keys[1]  # compiled and eager ascents agree to float32 rounding, amplified by Adam
    want = select_camera(env, q, q_params, actor, actor_params, env.reset(k),
                         jax.random.fold_in(k, 1), cfg).coords
    np.testing.assert_allclose(chk.coords[1], np.asarray(want), atol=2e-3)
    assert not np.allclose(chk.coords[0], chk.coords[1], atol=2e-3)  # each start its own
    default = jnp.tile(jnp.asarray(env.mount.default, jnp.float32), (3, 1))
    ret, ok = view_outcomes(env, actor, actor_params, keys, default)
    np.testing.assert_allclose(chk.default_return, np.asarray(ret), rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(chk.default, np.asarray(ok, np.float64))
    ret, ok = view_outcomes(env, actor, actor_params, keys, jnp.asarray(chk.coords, jnp.float32))
    np.testing.assert_allclose(chk.selected_return, np.asarray(ret), rtol=1e-5, atol=1e-5)
    # a different pose gives a different episode: the returns are not the default's copy
    assert not np.allclose(chk.selected_return, chk.default_return)
    doc = chk.as_dict()
    assert doc["episodes"] == 3 and len(doc["coords"]) == 3
    one = lambda *v: np.asarray(v, np.float64)  # noqa: E731
    z = np.zeros(2)
    assert CameraCheck(one(1, 1), one(1, 0), z, z, z).pays
    assert not CameraCheck(one(1, 0), one(0, 1), z, z, z).pays  # a tie keeps the default
    assert not CameraCheck(one(0, 0), one(1, 0), z, z, z).pays
