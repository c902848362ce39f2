"""The trainers' shared episode kit (``twinrl.learn.common``): ``vmap_scan`` is a vmap of scans,
and ``held_episodes`` is the task's own rollout, open or closed loop, on a short pendulum."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs
from twinrl.learn.common import Episodes, held_episodes, vmap_scan


def test_vmap_scan_equals_a_vmap_of_scans():
    # a carry that a per-example constant and the inputs turn batched, outputs of two kinds
    def body(c, x, k):
        c = {"a": c["a"] * k + x, "n": c["n"] + 1}
        return c, (c["a"].sum(), 2.0 * x)

    rng = np.random.default_rng(0)
    init = {"a": jnp.asarray(rng.normal(size=(4, 3))), "n": jnp.zeros(4, jnp.int32)}
    k, xs = jnp.asarray(rng.normal(size=4)), jnp.asarray(rng.normal(size=(4, 6, 3)))
    ref = jax.vmap(lambda c, k, x: jax.lax.scan(lambda c, x: body(c, x, k), c, x))(init, k, xs)
    out = vmap_scan(body, init, k, xs)
    for a, b in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_allclose(a, b, rtol=1e-6)
    assert out[1][1].shape == (4, 6, 3) and int(out[0]["n"][0]) == 6


def test_held_episodes_are_the_tasks_own_rollouts_open_and_closed_loop():
    env = envs.make("pendulum_swingup", episode_length=5)
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (3, 5, env.action_size), minval=-1.0,
                                 maxval=1.0)
    observe = lambda s, c: s.obs  # noqa: E731  (no camera: coords None)
    act = lambda o: jnp.tanh(o[:env.action_size])  # noqa: E731

    noise = 0.8 * actions  # DAgger's noisy visits: the policy's action plus this, clipped

    def closed_loop(key, noise):  # the reference: one episode, the policy acting on each obs
        def body(s, n):
            a = jnp.clip(act(s.obs) + n, -1.0, 1.0)
            s = env.step(s, a)
            return s, (a, s.reward)
        return jax.lax.scan(body, env.reset(key), noise, length=5)[1]

    @jax.jit  # one compile for all of it
    def run(keys, actions):
        return (held_episodes(env, observe, None, keys, actions),
                held_episodes(env, observe, act, keys),
                held_episodes(env, observe, act, keys, noise=noise),
                jax.vmap(lambda k, a: env.unroll(env.reset(k), a)[1])(keys, actions),
                jax.vmap(closed_loop)(keys, 0.0 * noise), jax.vmap(closed_loop)(keys, noise))

    open_loop, closed, noisy, rewards, (ref_actions, ref_rewards), ref_noisy = run(keys, actions)
    assert isinstance(open_loop, Episodes) and open_loop.rewards.shape == (3, 5)
    # open loop: the actions given, the rewards of env.unroll from the same resets
    np.testing.assert_allclose(open_loop.rewards, rewards, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(open_loop.actions, actions)
    np.testing.assert_array_equal(open_loop.obs, open_loop.states.obs)  # before each step
    # a task without ``success``: zeros
    np.testing.assert_array_equal(open_loop.success, np.zeros(3, np.float32))
    # closed loop: each action is the policy's of the observation before the step
    np.testing.assert_allclose(closed.actions, ref_actions, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(closed.rewards, ref_rewards, rtol=1e-5, atol=1e-6)
    assert not np.allclose(closed.rewards, open_loop.rewards)
    # noisy closed loop: the policy's action of each observation plus the noise, clipped, sent
    np.testing.assert_allclose(noisy.actions, ref_noisy[0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(noisy.rewards, ref_noisy[1], rtol=1e-5, atol=1e-6)
    assert np.abs(noisy.actions - closed.actions).max() > 0.1
    with pytest.raises(ValueError, match="actions or noise, not both"):
        held_episodes(env, observe, act, keys, actions, noise=noise)


def test_minibatch_fit_steps_alike_in_one_scan_and_one_call_a_step():
    # An image spec (a tiny CNN): "python" calls one compiled step at a time, "auto"'s choice for
    # images (XLA's CPU backend runs a convolution's gradient inside a loop body many times
    # slower); "scan" compiles them all. The same minibatches and updates either way, and the fit
    # lowers its loss.
    from twinrl.learn.common import make_minibatch_fit, make_optimizer, rgb_jitter
    from twinrl.learn.networks import NetworkConfig, make_network

    spec = {"pixels/c": (8, 8, 4), "state": (3,)}
    net = make_network(spec, 2, NetworkConfig(hidden=(16,), conv_features=(4,),
                                              conv_kernels=(3,), conv_strides=(2,), embed=8))
    params = net.init(jax.random.key(0))
    rng = np.random.default_rng(0)
    obs = {"pixels/c": jnp.asarray(rng.uniform(size=(40, 8, 8, 4)), jnp.float32),
           "state": jnp.asarray(rng.normal(size=(40, 3)), jnp.float32)}
    targets = jnp.asarray(np.tanh(rng.normal(size=(40, 2))), jnp.float32)
    weights = jnp.asarray(rng.uniform(0.5, 1.5, size=40), jnp.float32)
    tx = make_optimizer(1e-2, 1.0)
    out = {}
    for loop in ("python", "scan"):
        fit = make_minibatch_fit(net.apply, tx, 12, 16, rgb_jitter(0.1), loop=loop)
        out[loop] = fit(params, tx.init(params), obs, targets, 30, jax.random.key(1), weights)
    auto = make_minibatch_fit(net.apply, tx, 12, 16)
    assert auto.loop_for(obs) == "python"
    assert auto.loop_for({"state": obs["state"]}) == "scan"  # vectors: one compiled scan
    (pa, _, la), (pb, _, lb) = out["python"], out["scan"]
    assert la.shape == lb.shape == (12,)
    np.testing.assert_allclose(la, lb, rtol=1e-4, atol=1e-6)
    for a, b in zip(jax.tree_util.tree_leaves(pa), jax.tree_util.tree_leaves(pb)):
        np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-5)
    assert float(jnp.mean(la[-3:])) < float(la[0])
    with pytest.raises(ValueError, match="loop must be"):
        make_minibatch_fit(net.apply, tx, 1, 1, loop="while")
