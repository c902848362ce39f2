"""Learn@Sim on a user's own MJCF: ``envs.from_mjcf(path, reward=fn, reset_noise=...)`` gives a
task every trainer takes. A one-joint arm written for the tests (``tests/_turntable.py``: a
hinge in the horizontal plane with a motor, no gravity torque, no contact, a cheap compile)
learns with PODS to turn to a target angle from random starts, against a random policy; the
reward's shape and failures are one-line errors at ``from_mjcf``; the reset noise keeps
free-joint quaternions unit."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs
from twinrl.learn import pods
from twinrl.learn.pods import PODSConfig
from tests._turntable import ARM


DROP = """<mujoco><worldbody><geom type="plane" size="1 1 .1"/>
  <body pos="0 0 .3"><freejoint/><geom type="box" size=".05 .05 .05"/></body>
  <body pos=".3 0 .3"><joint type="ball"/><geom type="sphere" size=".05"/></body>
  <body pos="-.3 0 .3"><joint name="h" axis="0 1 0"/><geom type="sphere" size=".05"/></body>
</worldbody><actuator><motor joint="h" ctrlrange="-1 1"/></actuator></mujoco>"""

TARGET = 1.0  # rad


def turn(qpos, qvel, action):
    return {"angle": -(qpos[0] - TARGET) ** 2, "effort": -0.01 * jnp.sum(action ** 2)}


@pytest.fixture(scope="module")
def arm():
    return envs.from_mjcf(ARM, name="turntable", reward=turn, reset_noise=0.5,
                          episode_length=40, frame_skip=5)


def test_reward_terms_are_named_summed_and_logged(arm):
    assert arm.reward_term_names == ("angle", "effort")
    s = arm.reset(jax.random.key(1))
    s = arm.step(s, jnp.array([0.5]))
    q = float(s.pipeline_state.qpos[0])
    expected = -(q - TARGET) ** 2 - 0.01 * 0.25
    np.testing.assert_allclose(float(s.reward), expected, rtol=1e-5)
    np.testing.assert_allclose(float(s.metrics["reward/effort"]), -0.0025, rtol=1e-5)
    # a scalar reward is one term named "reward"
    env = envs.from_mjcf(ARM, reward=lambda q, v, a: jnp.cos(q[0]))
    assert env.reward_term_names == ("reward",)
    # without a reward every step's is 0, as before
    env = envs.from_mjcf(ARM)
    assert env.reward_term_names == () and float(env.step(env.reset(jax.random.key(0)),
                                                         jnp.ones(1)).reward) == 0.0


def test_reset_noise_is_bounded_and_keeps_quaternions_unit():
    env = envs.from_mjcf(DROP, reset_noise=0.2)
    m = env.sim.mj_model
    qpos, qvel = jax.vmap(env.initial_state)(jax.random.split(jax.random.key(0), 64))
    qpos, qvel = np.asarray(qpos), np.asarray(qvel)
    for a in (3, 7):  # the free joint's quaternion, the ball joint's
        np.testing.assert_allclose(np.linalg.norm(qpos[:, a:a + 4], axis=1), 1.0, rtol=1e-5)
    pos = qpos[:, :3] - m.qpos0[:3]
    assert np.all(np.abs(pos) <= 0.2 + 1e-6) and pos.std() > 0.05
    assert np.all(np.abs(qvel) <= 0.2 + 1e-6) and qvel.std() > 0.05
    same = envs.from_mjcf(DROP)
    np.testing.assert_allclose(np.asarray(same.initial_state(jax.random.key(0))[0]), m.qpos0,
                               rtol=1e-6)


@pytest.mark.parametrize("reward, match", [
    ("cos", "reward must be a function"),
    (lambda q, v, a: q, r"reward term 'reward' must be a scalar, got shape \(1,\)"),
    (lambda q, v, a: {"up": q[0], "bad": v}, "reward term 'bad' must be a scalar"),
    (lambda q, v, a: q[0] @ v, "reward\\(qpos, qvel, action\\) failed on the reset state"),
])
def test_bad_rewards_are_one_line_errors(reward, match):
    with pytest.raises((TypeError, ValueError), match=match) as e:
        envs.from_mjcf(ARM, reward=reward)
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="reset_noise"):
        envs.from_mjcf(ARM, reset_noise=-1.0)


def _random_return(env, episodes=16, seed=0):
    """The mean return of uniform random actions in [-1, 1]."""
    def one(k):
        k0, k1 = jax.random.split(k)
        acts = jax.random.uniform(k1, (env.episode_length, env.action_size), minval=-1.0,
                                  maxval=1.0)
        return env.unroll(env.reset(k0), acts)[1].sum()
    return float(jnp.mean(jax.vmap(one)(jax.random.split(jax.random.key(seed), episodes))))


def test_pods_learns_to_turn_the_users_arm(arm):
    """PODS, its analytic gradients through the user's MJCF and reward: measured (seeds 0 and
    1), random actions return -54 / -51 and doing nothing -48; the learned policy -31 / -24
    after one epoch, -2.9 / -4.7 after eight (the best of the last three: -2.9 / -3.5)."""
    cfg = PODSConfig(epochs=8, batch_size=8, rollout_length=40, horizon=20, line_search_steps=4,
                     step_size=1.0, regression_steps=32, hidden=(32, 32), eval_episodes=8,
                     eval_length=40)
    _, _, metrics = pods.train(arm, cfg, jax.random.key(0))
    rand = _random_return(arm)
    best = max(metrics["return"][-3:])
    assert np.all(np.isfinite(metrics["return"]))
    assert best > 0.25 * rand, (rand, metrics["return"])  # a quarter of the loss


def _frames(path) -> np.ndarray:
    import warnings

    import imageio.v2 as imageio

    with warnings.catch_warnings():  # ffmpeg is exec'd at once: JAX's at-fork warning is moot
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called")
        with imageio.get_reader(path) as reader:  # closed: no ResourceWarning from its pipe
            return np.stack([f for f in reader.iter_data()])


def test_policy_video_of_a_users_mjcf_without_cameras(arm, tmp_path):
    """``runner.policy_video`` draws an episode of any task, a user's MJCF with no camera
    included (where MuJoCo's viewer opens), one frame per control step, the arm moving."""
    from twinrl.learn.networks import make_policy
    from twinrl.learn.runner import policy_video

    assert arm.sim.mj_model.ncam == 0
    pol = make_policy(arm.observation_size, arm.action_size, (8,))
    params = pol.init(jax.random.key(0))
    push = lambda p, obs: jnp.ones(1)  # noqa: E731  (turns the arm at full torque)
    path = policy_video(arm, push, params, tmp_path / "turn.mp4", size=(64, 48), steps=12)
    frames = _frames(path)
    assert frames.shape[:3] == (12, 48, 64)
    assert np.abs(frames[-1].astype(float) - frames[0]).mean() > 0.5  # it turned
    path = policy_video(arm, pol, params, tmp_path / "net.mp4", size=(64, 48), steps=3)
    assert _frames(path).shape[0] == 3
