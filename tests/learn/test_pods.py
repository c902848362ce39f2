"""``twinrl.learn.pods``: the trainer contract, determinism, kill/resume equivalence, learning on
a short cartpole swing-up, the second order on the 2-D push through contacts, and two emulated
devices against one.

Every test of a config shares one compiled set of functions (``pods._build`` is memoised per env
and config, epochs aside), so the module pays one MJX gradient compile per config: cartpole
(first order), push (Gauss–Newton) and the two-device subprocess. Measured with a cold
compilation cache on the shared 2-core dev machine (load ~7): 987 s wall, 443 s CPU, almost all
of it XLA compiling the three configs (push's Gauss–Newton through contacts: 344 s wall); the
tests themselves run in ~7 s once compiled.
"""

import json
import os
import subprocess
import sys
import textwrap
from unittest import mock

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs
from twinrl.learn import pods, trajopt
from twinrl.learn.pods import PODSConfig

# A short cartpole problem: 40-step rollouts cut into two 20-step windows, 40-step evaluations.
SMALL = dict(batch_size=4, rollout_length=40, horizon=20, line_search_steps=4, step_size=1.0,
             regression_steps=32, hidden=(32, 32), eval_episodes=4, eval_length=40)
EPOCHS = 8
CUT = 3  # the epoch the "killed" run stops at

CONTRACT_KEYS = {"epoch", "env_steps", "wall_s", "return", "grad_norm", "accepted_frac",
                 "skipped", "nonfinite", "improvement", "alpha", "loss", "rollout_return"}


def _tree_equal(a, b, atol=0.0):
    la, lb = jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=atol)


@pytest.fixture(scope="module")
def pendulum():
    # cartpole_swingup, not the pendulum: no joint limit, so no constraint solve in the compiled
    # gradient (about half the compile time; the suite is compile-bound).
    return envs.make("cartpole_swingup")


@pytest.fixture(scope="module")
def small_run(pendulum):
    """EPOCHS epochs of the small config, with every epoch's train state captured."""
    captured = {}
    progress = []

    def checkpoint_fn(epoch, state, metrics):
        captured[epoch] = (jax.tree_util.tree_map(np.array, state),
                           {k: list(v) for k, v in metrics.items()})

    cfg = PODSConfig(epochs=EPOCHS, **SMALL)
    policy, params, metrics = pods.train(pendulum, cfg, jax.random.PRNGKey(0),
                                         progress_fn=lambda e, m: progress.append((e, m)),
                                         checkpoint_fn=checkpoint_fn)
    return cfg, policy, params, metrics, captured, progress


def test_contract_metrics_and_finite_params(pendulum, small_run):
    cfg, policy, params, metrics, captured, progress = small_run
    assert CONTRACT_KEYS <= set(metrics)
    assert all(len(v) == EPOCHS for v in metrics.values())
    assert metrics["epoch"] == list(range(1, EPOCHS + 1))
    per_epoch = cfg.batch_size * 2 * (20 + 20 * (1 + 4))  # rollout + (grad + 4 candidates)
    assert cfg.steps_per_epoch(pendulum) == per_epoch
    assert metrics["env_steps"] == [per_epoch * (e + 1) for e in range(EPOCHS)]
    assert np.all(np.diff(metrics["wall_s"]) >= 0)
    assert [e for e, _ in progress] == metrics["epoch"]
    assert sorted(captured) == metrics["epoch"]
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(params))
    for k in ("return", "loss", "accepted_frac", "rollout_return"):
        assert np.all(np.isfinite(metrics[k])), k
    # a fraction of the epoch's 4 x 2 windows; the line search improved some of them, and the
    # mean return gain is positive exactly in the epochs where it did
    windows = cfg.batch_size * (cfg.rollout_length // cfg.horizon)
    accepted = np.asarray(metrics["accepted_frac"]) * windows
    np.testing.assert_allclose(accepted, np.round(accepted), atol=1e-9)
    assert accepted.max() > 0
    np.testing.assert_array_equal(np.asarray(metrics["improvement"]) > 0, accepted > 0)
    # the pendulum's gradients are finite: no window is skipped for a nonfinite one
    assert all(s == 0 for s in metrics["skipped"]) and all(n == 0 for n in metrics["nonfinite"])
    obs = pendulum.reset(jax.random.PRNGKey(3)).obs
    a = policy.apply(params, obs)
    assert a.shape == (1,) and abs(float(a[0])) <= 1.0


def test_learning_improves_the_return(small_run):
    *_, metrics, _, _ = small_run
    ret = metrics["return"]
    # measured: 2.31 at epoch 1 rising every epoch to 3.21 by epoch 8 (40-step cartpole
    # episodes from hanging, where a policy that does nothing earns about 2)
    assert max(ret[-3:]) > 1.25 * ret[0], ret
    assert np.mean(metrics["improvement"]) > 0


def test_same_seed_same_metrics(pendulum, small_run):
    cfg, _, params, metrics, _, _ = small_run
    _, params2, metrics2 = pods.train(pendulum, cfg, jax.random.PRNGKey(0))
    for k in metrics:
        if k != "wall_s":
            assert metrics[k] == metrics2[k], k
    _tree_equal(params, params2)
    # and a typed key of the same seed is the same seed
    _, params3, _ = pods.train(pendulum, PODSConfig(epochs=1, **SMALL), jax.random.key(0))
    _tree_equal(captured_params(small_run, 1), params3)


def captured_params(small_run, epoch):
    return small_run[4][epoch][0].params


def test_resume_equals_uninterrupted(pendulum, small_run):
    cfg, _, params, metrics, captured, _ = small_run
    state, history = captured[CUT]
    seen = {}

    def restore(template):
        seen["template"] = template
        return state, history

    progress = []
    _, params2, metrics2 = pods.train(pendulum, cfg, jax.random.PRNGKey(0), restore=restore,
                                      progress_fn=lambda e, m: progress.append(e))
    assert jax.tree_util.tree_structure(seen["template"]) == jax.tree_util.tree_structure(state)
    assert progress == list(range(CUT + 1, EPOCHS + 1))
    _tree_equal(params, params2)
    for k in metrics:
        if k != "wall_s":
            assert metrics[k] == metrics2[k], k
    # a restored state that disagrees with its metrics is refused
    with pytest.raises(ValueError, match="epoch"):
        pods.train(pendulum, cfg, 0, restore=lambda t: (state, captured[CUT + 1][1]))


def test_config_errors():
    for bad, word in [(dict(batch_size=0), "batch_size"), (dict(horizon=0), "horizon"),
                      (dict(rollout_length=10, horizon=20), "horizon"),
                      (dict(order=3), "order"), (dict(learning_rate=0.0), "learning_rate"),
                      (dict(max_grad_norm=-1.0), "max_grad_norm"),
                      (dict(max_step_norm=0.0), "max_step_norm"), (dict(gamma=1.0), "gamma"),
                      (dict(lam=1.5), "lam"), (dict(critic_steps=0), "critic_steps"),
                      (dict(critic_learning_rate=0.0), "critic_learning_rate")]:
        with pytest.raises(ValueError, match=word):
            PODSConfig(**bad)
    with pytest.raises(TypeError, match="PODSConfig"):
        pods.train(None, trajopt.TrajoptConfig())


# ----------------------------------------------------------------------------- critic
def test_critic_targets_are_td_lambda_returns():
    rng = np.random.default_rng(0)
    B, T, gamma = 2, 7, 0.9
    obs = rng.standard_normal((B, T, 3)).astype(np.float32)
    final_obs = rng.standard_normal((B, 3)).astype(np.float32)
    rewards = rng.uniform(0, 1, (B, T)).astype(np.float32)
    valid = np.ones((B, T), bool)
    valid[1, 5:] = False  # rollout 1 diverged after its 5th step
    final_valid = valid[:, -1].copy()
    value = lambda o: np.asarray(o, np.float64).sum(-1)  # noqa: E731
    args = (obs, rewards, valid, final_obs, final_valid, gamma)
    # lambda = 1: the discounted return, bootstrapped with V(final) at the truncation
    g1 = np.asarray(pods.critic_targets(lambda o: jnp.sum(o, -1), *args, 1.0))
    v_final = value(final_obs)
    for t in range(T):
        ref = sum(gamma ** (k - t) * rewards[0, k] for k in range(t, T)) \
            + gamma ** (T - t) * v_final[0]
        np.testing.assert_allclose(g1[0, t], ref, rtol=1e-5)
    for t in range(4):  # rollout 1 ends at its last live step: nothing after it
        ref = sum(gamma ** (k - t) * rewards[1, k] for k in range(t, 5))
        np.testing.assert_allclose(g1[1, t], ref, rtol=1e-5)
    # lambda = 0: one-step TD targets r_t + gamma V(s_{t+1})
    g0 = np.asarray(pods.critic_targets(lambda o: jnp.sum(o, -1), *args, 0.0))
    v = value(obs)
    np.testing.assert_allclose(g0[0, :-1], rewards[0, :-1] + gamma * v[0, 1:], rtol=1e-5)
    np.testing.assert_allclose(g0[0, -1], rewards[0, -1] + gamma * v_final[0], rtol=1e-5)


def test_critic_is_fitted_and_bootstraps_the_windows(pendulum):
    cfg = PODSConfig(epochs=4, critic=True, critic_steps=16, **SMALL)
    states = {}
    _, params, metrics = pods.train(pendulum, cfg, jax.random.PRNGKey(0),
                                    checkpoint_fn=lambda e, st, m: states.__setitem__(e, st))
    for k in ("value_loss", "value_loss_before", "value", "return", "loss"):
        assert len(metrics[k]) == 4 and np.all(np.isfinite(metrics[k])), k
    # every epoch's fit lowers the TD(lambda) error it starts from
    assert np.all(np.array(metrics["value_loss"]) < np.array(metrics["value_loss_before"]))
    assert metrics["value"][-1] > 0  # rewards are >= 0
    assert max(metrics["accepted_frac"]) > 0
    assert metrics["env_steps"][-1] == 4 * cfg.steps_per_epoch(pendulum)  # no extra simulation
    c1, c4 = states[1].critic_params, states[4].critic_params
    assert any(not np.allclose(a, b) for a, b in zip(jax.tree_util.tree_leaves(c1),
                                                     jax.tree_util.tree_leaves(c4)))
    # the critic-less run carries an (untouched) critic of the same structure
    assert (jax.tree_util.tree_structure(states[1])
            == jax.tree_util.tree_structure(captured_state(pendulum)))


def captured_state(env):
    seen = {}
    pods.train(env, PODSConfig(epochs=1, **SMALL), 0,
               checkpoint_fn=lambda e, st, m: seen.setdefault("s", st))
    return seen["s"]


def test_tuned_cartpole_configs_use_the_critic():
    from twinrl.learn import runner
    for algo in ("pods", "pods2"):
        cfg = runner.make_config(algo, "cartpole_swingup")
        assert cfg.critic and cfg.trajopt_config().discount == cfg.gamma
        assert cfg.order == (2 if algo == "pods2" else 1)
    assert runner.make_config("pods", "pendulum_swingup").critic is False
    assert PODSConfig().trajopt_config().discount == 1.0  # PODS's plain return by default


# ----------------------------------------------------------------------------- push, order 2
def test_second_order_on_push_with_a_2d_action():
    env = envs.make("push")
    assert env.action_size == 2
    cfg = PODSConfig(epochs=3, order=2, batch_size=2, rollout_length=10, horizon=5,
                     line_search_steps=3, regularization=1e-2, regression_steps=8,
                     hidden=(16, 16), eval_episodes=2, eval_length=10)
    calls = {"gn": 0, "first": 0}
    gn, first = trajopt.gauss_newton_direction, trajopt.first_order_direction

    def spy_gn(*a, **k):
        calls["gn"] += 1
        return gn(*a, **k)

    def spy_first(*a, **k):
        calls["first"] += 1
        return first(*a, **k)

    with mock.patch.object(trajopt, "gauss_newton_direction", spy_gn), \
            mock.patch.object(trajopt, "first_order_direction", spy_first):
        policy, params, metrics = pods.train(env, cfg, 1)
    assert calls["gn"] >= 1 and calls["first"] == 0  # traced through the Gauss-Newton step
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(params))
    assert np.all(np.isfinite(metrics["return"]))
    # the windows' mean return gain is positive exactly in the epochs where some were improved
    assert sum(metrics["accepted_frac"]) > 0
    np.testing.assert_array_equal(np.asarray(metrics["improvement"]) > 0,
                                  np.asarray(metrics["accepted_frac"]) > 0)
    assert all(n == 0 for n in metrics["nonfinite"])  # gradients through the contacts finite
    assert metrics["env_steps"][-1] == 3 * 2 * 2 * (5 + 5 * (1 + 3))


# ----------------------------------------------------------------------------- devices
TWO_DEVICES = textwrap.dedent("""
    import json, sys
    import jax, numpy as np
    from twinrl import envs
    from twinrl.learn import pods
    assert len(jax.devices()) == 2, jax.devices()
    cfg = pods.PODSConfig(**json.loads(sys.argv[1]))
    _, params, metrics = pods.train(envs.make("cartpole_swingup"), cfg, jax.random.PRNGKey(0))
    leaves = [np.asarray(x).ravel().tolist() for x in jax.tree_util.tree_leaves(params)]
    print("RESULT" + json.dumps({"metrics": metrics, "params": leaves}))
""")


def test_two_emulated_devices_equal_one(pendulum, small_run):
    cfg = dict(SMALL, epochs=2)
    # The parent's compiler flags (the suite runs XLA at -O0) plus two emulated devices.
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    out = subprocess.run([sys.executable, "-c", TWO_DEVICES, json.dumps(cfg)],
                         capture_output=True, text=True, env=env, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    line = next(ln for ln in out.stdout.splitlines() if ln.startswith("RESULT"))
    two = json.loads(line[len("RESULT"):])
    one_params = captured_params(small_run, 2)
    one_metrics = small_run[4][2][1]
    # Not bit for bit: each device compiles the rollouts for its half batch and XLA fuses float32
    # operations differently (tests/physics/test_sharding.py); decisions must agree.
    for k in ("env_steps", "accepted_frac", "skipped", "nonfinite"):
        assert two["metrics"][k] == one_metrics[k], k
    np.testing.assert_allclose(two["metrics"]["return"], one_metrics["return"], rtol=1e-4)
    for x, y in zip(jax.tree_util.tree_leaves(one_params), two["params"]):
        np.testing.assert_allclose(np.asarray(x).ravel(), y, rtol=1e-3, atol=1e-5)
