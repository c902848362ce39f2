"""``twinrl.learn.shac``: the trainer contract, determinism, kill/resume equivalence, the NaN
guard, TD(lambda) targets on a hand example, and learning on a short pendulum run.

Compiles dominate. The contract tests use ``PointMass`` (a pure-JAX double integrator, Brax's habit
of a trivial env for fast tests: its epoch compiles in a few seconds); only the learning test
compiles SHAC's gradient through MJX (pendulum, ~45-70 s cold on the 2-core dev machine, ~5 s
with a warm compilation cache).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs import base as brax_base

from twinrl import envs
from twinrl.learn import common, shac
from twinrl.learn.shac import SHACConfig, td_lambda_targets


class PointMass(brax_base.Env):
    """A 1-D double integrator pushed towards the origin: obs ``[x, v]``, action a force in
    [-1, 1], reward ``exp(-x^2 / 0.1)`` in [0, 1]. Differentiable, compiles in seconds."""

    episode_length = 20

    def __init__(self, nan_reward: bool = False):
        self.nan_reward = nan_reward

    def reset(self, rng):
        q = jax.random.uniform(rng, (2,), minval=-1.0, maxval=1.0) * jnp.array([1.0, 0.2])
        zero = jnp.zeros(())
        return brax_base.State(pipeline_state=q, obs=q, reward=zero, done=zero, metrics={},
                               info={})

    def step(self, state, action):
        x, v = state.pipeline_state
        v = v + 0.1 * jnp.clip(action[0], -1.0, 1.0)
        x = x + 0.1 * v
        q = jnp.stack([x, v])
        r = jnp.exp(-x**2 / 0.1)
        if self.nan_reward:
            r = r * jnp.nan
        return state.replace(pipeline_state=q, obs=q, reward=r)

    @property
    def observation_size(self):
        return 2

    @property
    def action_size(self):
        return 1

    @property
    def backend(self):
        return "jax"


TINY = SHACConfig(epochs=4, num_envs=8, horizon=8, critic_iterations=2, critic_minibatches=2,
                  actor_hidden=(16,), critic_hidden=(16,), eval_episodes=2)


class Kill(Exception):
    pass


@pytest.fixture(scope="module")
def full_run():
    rows = []
    states = []
    out = shac.train(PointMass(), TINY, jax.random.PRNGKey(3),
                     progress_fn=lambda e, m: rows.append((e, m)),
                     checkpoint_fn=lambda e, s, m: states.append((e, s)))
    return out, rows, states


@pytest.fixture(scope="module")
def killed_and_resumed():
    """Run TINY, 'kill' it after epoch 2 (checkpoint_fn raises), resume from the captured state."""
    saved = {}

    def checkpoint(epoch, state, metrics):
        saved["state"] = jax.tree_util.tree_map(np.asarray, state)  # as a checkpoint holds it
        saved["metrics"] = metrics
        if epoch == 2:
            raise Kill

    with pytest.raises(Kill):
        shac.train(PointMass(), TINY, jax.random.PRNGKey(3), checkpoint_fn=checkpoint)
    killed_metrics = saved["metrics"]
    seen = {}

    def restore(template):
        assert jax.tree_util.tree_structure(template) == jax.tree_util.tree_structure(
            saved["state"])
        seen["template_epoch"] = int(template.epoch)
        return saved["state"], saved["metrics"]

    resumed = shac.train(PointMass(), TINY, jax.random.PRNGKey(3), restore=restore)
    return killed_metrics, resumed, seen


def test_contract(full_run):
    (policy, params, metrics), rows, states = full_run
    E, N, h = TINY.epochs, TINY.num_envs, TINY.horizon
    for k in ("epoch", "env_steps", "wall_s", "return", "grad_norm", "skipped"):
        assert len(metrics[k]) == E, k
    assert metrics["epoch"] == [1.0, 2.0, 3.0, 4.0]
    assert metrics["env_steps"] == [float(e * N * h) for e in range(1, E + 1)]
    assert np.all(np.diff(metrics["wall_s"]) > 0)
    assert all(np.isfinite(metrics[k]).all() for k in metrics)
    assert [e for e, _ in rows] == [1, 2, 3, 4] and [e for e, _ in states] == [1, 2, 3, 4]
    assert rows[-1][1]["return"] == metrics["return"][-1]
    assert isinstance(states[-1][1], shac.SHACState) and int(states[-1][1].epoch) == E
    # The returned policy is a plain obs -> action network with actions in [-1, 1].
    obs = jnp.array([[3.0, -2.0], [0.1, 0.0], [-50.0, 9.0]])
    a = policy.apply(params, obs)
    assert a.shape == (3, 1) and np.all(np.abs(np.asarray(a)) <= 1.0)
    assert policy.config.output == "tanh"
    ret = common.evaluate(PointMass(), policy.apply, params, jax.random.PRNGKey(0), episodes=2)
    assert ret.shape == (2,) and np.all((ret >= 0) & (ret <= PointMass.episode_length))


def test_deterministic_and_resume_equals_uninterrupted(full_run, killed_and_resumed):
    (_, params, metrics), _, _ = full_run
    killed_metrics, (_, resumed_params, resumed_metrics), seen = killed_and_resumed
    assert seen["template_epoch"] == 0
    # Same seed, separate runs: identical numbers (determinism) ...
    for k in ("return", "grad_norm", "actor_loss", "critic_loss"):
        assert killed_metrics[k] == metrics[k][:2], k
    # ... and the resumed run continues the killed one exactly.
    assert resumed_metrics["epoch"] == metrics["epoch"]
    for k in metrics:
        if k != "wall_s":
            assert resumed_metrics[k] == metrics[k], k
    jax.tree_util.tree_map(np.testing.assert_array_equal, resumed_params, params)


def test_restore_mismatched_epoch_is_refused(full_run):
    _, _, states = full_run
    state = states[1][1]  # after epoch 2
    with pytest.raises(ValueError, match="epoch 2"):
        shac.train(PointMass(), TINY, jax.random.PRNGKey(3),
                   restore=lambda t: (state, {"epoch": [1.0]}))


def test_nan_guard_skips_every_nonfinite_update():
    cfg = dataclasses.replace(TINY, epochs=2)
    states = []
    policy, params, metrics = shac.train(PointMass(nan_reward=True), cfg, jax.random.PRNGKey(0),
                                         checkpoint_fn=lambda e, s, m: states.append(s))
    assert metrics["skipped"] == [1.0, 2.0]
    assert metrics["critic_skipped"] == [2.0 * 2, 4.0 * 2]  # iterations * minibatches per epoch
    s = states[-1]
    leaves = jax.tree_util.tree_leaves((s.actor, s.critic, s.target_critic, s.actor_opt,
                                        s.critic_opt))
    assert all(np.isfinite(np.asarray(x)).all() for x in leaves)
    # Every update was dropped, and Adam's moments stayed 0: the policy is the initial one.
    init = shac.make_networks(2, 1, cfg)[0].init(jax.random.split(jax.random.PRNGKey(0), 4)[0])
    jax.tree_util.tree_map(np.testing.assert_array_equal, s.actor["policy"], init)
    # The returned params are those with the observation standardisation folded in.
    obs = jnp.array([[0.3, -0.2], [1.0, 0.5]])
    std = np.sqrt(np.asarray(s.obs_norm["var"]) + 1e-2)
    np.testing.assert_allclose(policy.apply(params, obs), policy.apply(
        init, (obs - s.obs_norm["mean"]) / std), rtol=1e-5, atol=1e-6)


def test_td_lambda_targets_by_hand():
    g, lam = 0.9, 0.5
    r = np.array([1.0, 2.0, 3.0])
    v = np.array([10.0, 20.0, 30.0])  # next_values[t] = V(s_{t+1})
    # No episode end inside: the window's end (t = 2) is the only boundary.
    G2 = 3 + g * 30
    G1 = 2 + g * ((1 - lam) * 20 + lam * G2)
    G0 = 1 + g * ((1 - lam) * 10 + lam * G1)
    out = td_lambda_targets(r, v, np.array([False, False, True]), g, lam)
    np.testing.assert_allclose(out, [G0, G1, G2], rtol=1e-6)
    # The same as the lambda-weighted n-step returns from s0.
    n1, n2, n3 = 1 + g * 10, 1 + g * 2 + g**2 * 20, 1 + g * 2 + g**2 * 3 + g**3 * 30
    np.testing.assert_allclose(out[0], (1 - lam) * n1 + (1 - lam) * lam * n2 + lam**2 * n3,
                               rtol=1e-6)
    # An episode ends after step 0 (bootstrap on V(s1) = 10 only), steps 1-2 are a new episode;
    # lambda = 1 is the Monte-Carlo return, lambda = 0 one-step TD.
    b = np.array([True, False, True])
    np.testing.assert_allclose(td_lambda_targets(r, v, b, g, lam),
                               [1 + g * 10, G1, G2], rtol=1e-6)
    np.testing.assert_allclose(td_lambda_targets(r, v, b, g, 1.0), [1 + g * 10, 2 + g * G2, G2],
                               rtol=1e-6)
    np.testing.assert_allclose(td_lambda_targets(r, v, b, g, 0.0), r + g * v, rtol=1e-6)
    # Trailing axes (environments) are independent columns.
    two = td_lambda_targets(np.stack([r, r], 1), np.stack([v, v], 1),
                            np.stack([b, np.array([False, False, True])], 1), g, lam)
    np.testing.assert_allclose(two[:, 1], [G0, G1, G2], rtol=1e-6)


def test_config_errors_name_the_field():
    with pytest.raises(ValueError, match="critic_minibatches"):
        SHACConfig(num_envs=6, horizon=5, critic_minibatches=4)
    with pytest.raises(ValueError, match="gamma"):
        SHACConfig(gamma=1.5)
    with pytest.raises(ValueError, match="horizon"):
        SHACConfig(horizon=0)


def test_learns_cartpole_swingup():
    """A short SHAC run through MJX improves the deterministic return well past the start's
    (cartpole: no joint limit, so no constraint solve to compile)."""
    env = envs.make("cartpole_swingup", episode_length=100)
    cfg = SHACConfig(epochs=20, num_envs=16, horizon=32, eval_episodes=4, actor_lr=5e-3)
    _, params, metrics = shac.train(env, cfg, jax.random.PRNGKey(0))
    assert metrics["skipped"][-1] == 0
    first, best = metrics["return"][0], max(metrics["return"][-5:])
    assert best > first + 5.0, metrics["return"]
