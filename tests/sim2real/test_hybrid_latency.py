"""HDS's learned-dynamics rollouts (``twinrl.sim2real.hybrid.make_dynamics``) on an env whose
``System`` delays actions: the residual sees the *executed* action (the one leaving the delay's
queue), and the wrapper's queue advances exactly as under ``env.step``."""

import dataclasses
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs
from twinrl.envs.wrappers import QUEUE_KEY
from twinrl.learn.networks import NetworkConfig, make_network
from twinrl.sim2real import hybrid

ACTIONS = jnp.array([[0.9], [-0.6], [0.3], [1.0]])


@pytest.fixture(scope="module")
def delayed():
    base = envs.make("pendulum_swingup", episode_length=20)
    env = envs.make("pendulum_swingup", episode_length=20,
                    system=dataclasses.replace(envs.system_of(base), latency=1))
    assert isinstance(env, envs.LatencyWrapper) and env.latency == 1
    return env


def _rollout(step, state, actions):
    out = []
    for a in actions:
        state = step(state, a)
        out.append(state)
    return out


def test_zero_residual_rollout_is_the_delayed_env(delayed):
    env = delayed
    nq, nv = env.sim.nq, env.sim.nv
    obs_size, act = int(env.observation_size), int(env.action_size)
    net = make_network(obs_size + act, nq + nv, NetworkConfig(hidden=(4,), output="linear"))
    zero = hybrid.HybridModel(net, jax.tree.map(jnp.zeros_like, net.init(jax.random.key(0))),
                              jnp.zeros(obs_size + act), jnp.ones(obs_size + act),
                              jnp.ones(nq + nv), latency=1)
    s0 = env.reset(jax.random.key(1))
    model = _rollout(jax.jit(hybrid.make_dynamics(env, zero)), s0, ACTIONS)
    sim = _rollout(jax.jit(env.step), s0, ACTIONS)
    for m, s in zip(model, sim):
        # equal up to float32 rounding (the two steps compile separately)
        np.testing.assert_allclose(np.asarray(m.obs), np.asarray(s.obs), rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(np.asarray(m.reward), np.asarray(s.reward), rtol=1e-6)
        np.testing.assert_array_equal(np.asarray(m.info[QUEUE_KEY]),
                                      np.asarray(s.info[QUEUE_KEY]))
    # the queue advances: after step t it holds the action sent at t
    for t, m in enumerate(model):
        np.testing.assert_array_equal(np.asarray(m.info[QUEUE_KEY]), np.asarray(ACTIONS[t:t + 1]))
    # and the delay is real: the first step executed the empty queue's zero, not ACTIONS[0]
    bare = envs.make("pendulum_swingup", episode_length=20)
    undelayed = jax.jit(bare.step)(bare.reset(jax.random.key(1)), ACTIONS[0])
    assert not np.allclose(np.asarray(undelayed.obs), np.asarray(model[0].obs))


def test_the_residual_sees_the_executed_action(delayed):
    env = delayed
    nq, nv = env.sim.nq, env.sim.nv
    seen = []

    def residual(obs, applied):  # a velocity kick proportional to the action it is given
        seen.append(applied)
        return jnp.zeros(nq + nv).at[nq].set(0.5 * applied[0])

    dyn = jax.jit(hybrid.make_dynamics(env, SimpleNamespace(residual=residual)))
    step = jax.jit(env.step)
    s = env.reset(jax.random.key(2))
    for a in ACTIONS:
        queued = s.info[QUEUE_KEY][0]
        m, plain = dyn(s, a), step(s, a)
        dv = np.asarray(m.pipeline_state.qvel) - np.asarray(plain.pipeline_state.qvel)
        np.testing.assert_allclose(dv, [0.5 * float(queued[0])], atol=1e-6)
        np.testing.assert_array_equal(np.asarray(m.info[QUEUE_KEY]),
                                      np.asarray(plain.info[QUEUE_KEY]))
        s = plain   # continue from the simulator, so each step's kick is checked on its own
    assert len(seen) == 1   # traced once


def test_after_an_auto_reset_the_residual_sees_the_emptied_queue(delayed):
    # Brax's AutoResetWrapper sets info["steps"] back to 0 on a new episode: the wrapper then
    # empties its queue, and the model must see the zero the simulator executes
    env = delayed
    nq, nv = env.sim.nq, env.sim.nv

    def residual(obs, applied):
        return jnp.zeros(nq + nv).at[nq].set(0.5 * applied[0])

    dyn = jax.jit(hybrid.make_dynamics(env, SimpleNamespace(residual=residual)))
    s = env.reset(jax.random.key(3))
    info = {**s.info, QUEUE_KEY: jnp.full_like(s.info[QUEUE_KEY], 0.8), "steps": jnp.zeros(()),
            "latency/steps_seen": jnp.full((), 5.0)}
    s = s.replace(info=info)
    assert float(env.executed(s)[0]) == 0.0
    m, plain = dyn(s, ACTIONS[0]), jax.jit(env.step)(s, ACTIONS[0])
    np.testing.assert_allclose(np.asarray(m.pipeline_state.qvel),
                               np.asarray(plain.pipeline_state.qvel), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(m.info[QUEUE_KEY]), np.asarray(ACTIONS[:1]))
