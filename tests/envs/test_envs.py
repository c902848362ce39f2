"""Every registered task: jit/vmap reset and step, smooth bounded rewards, gradients of the return.

One parameterised test per property over ``envs.names()`` (MuJoCo Playground's habit), so a new
task is tested by registering it. Compiles are the cost here: each task compiles one batched
``step`` and one ``value_and_grad`` of a short episode, nothing more.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs

NAMES = envs.names("twinrl")  # the Control Suite's: tests/envs/test_dmc.py
# The gradient test compiles a value_and_grad per task. cartpole_balance is cartpole_swingup's
# model, step and reward with another reset distribution (test_balance_and_swingup_share_a_model),
# so it is compiled there once, as cartpole_swingup. push's gradients through contacts are checked
# against float64 finite differences (tests/physics/test_gradcheck.py), vmapped in float32
# (tests/physics/test_solver.py) and through PODS training (tests/learn/test_pods.py); a fourth
# compile of its episode gradient here cost 69 s of the suite's budget.
MODELS = [n for n in NAMES if n not in ("cartpole_balance", "push")]
BATCH, STEPS, HORIZON = 4, 10, 30


@pytest.fixture(scope="module")
def made():
    return {name: envs.make(name) for name in NAMES}


def test_registry_lists_the_tasks():
    assert set(NAMES) == {"pendulum_swingup", "cartpole_balance", "cartpole_swingup", "push",
                          "peg_insertion", "spatula_flipping", "needle_threading"}


@pytest.mark.parametrize("name", NAMES)
def test_reset_and_step_jit_without_nan(name, made):
    env = made[name]
    reset = jax.jit(jax.vmap(env.reset))
    step = jax.jit(jax.vmap(env.step))
    state = reset(jax.random.split(jax.random.PRNGKey(0), BATCH))
    assert state.obs.shape == (BATCH, env.observation_size)
    assert state.obs.dtype == jnp.float32
    # the reset distribution is random: different keys, different initial states
    assert np.ptp(np.asarray(state.pipeline_state.qpos), axis=0).max() > 0
    terms = {f"reward/{k}" for k in env.reward_term_names}
    assert set(state.metrics) == terms
    actions = jax.random.uniform(jax.random.PRNGKey(1), (STEPS, BATCH, env.action_size),
                                 minval=-1.0, maxval=1.0)
    for a in actions:
        state = step(state, a)
        for leaf in (state.obs, state.reward, state.pipeline_state.qpos,
                     state.pipeline_state.qvel, *state.metrics.values()):
            assert np.all(np.isfinite(np.asarray(leaf))), name
        r = np.asarray(state.reward)
        assert np.all((r >= 0) & (r <= 1)), r
        for k in terms:
            m = np.asarray(state.metrics[k])
            assert np.all((m >= 0) & (m <= 1)), (k, m)
        assert not np.any(np.asarray(state.done))
    # the logged terms are what the reward is made of
    combined = jax.vmap(lambda m: env.combine({k: m[f"reward/{k}"] for k in env.reward_term_names}))
    np.testing.assert_allclose(combined(state.metrics), state.reward, rtol=1e-6)


def _episode_actions(env, key):
    return 0.5 * jax.random.uniform(key, (HORIZON, env.action_size), minval=-1.0, maxval=1.0)


def test_balance_and_swingup_share_a_model(made):
    bal, up = made["cartpole_balance"], made["cartpole_swingup"]
    assert type(bal) is type(up) and bal.scene == up.scene
    assert dataclasses.replace(bal.config, swingup=True) == up.config
    assert bal.sim.mj_model.nq == up.sim.mj_model.nq
    s = up.reset(jax.random.PRNGKey(0))
    a = jnp.full((up.action_size,), 0.3)
    nb, nu = jax.jit(bal.step)(s, a), jax.jit(up.step)(s, a)  # same state in, same state out
    np.testing.assert_array_equal(nb.pipeline_state.qpos, nu.pipeline_state.qpos)
    np.testing.assert_array_equal(nb.reward, nu.reward)


@pytest.mark.parametrize("name", MODELS)
def test_grad_of_episode_return_wrt_actions_is_finite(name, made):
    env = made[name]
    s0 = env.reset(jax.random.PRNGKey(2))

    def episode_return(actions):
        _, rewards = env.unroll(s0, actions)
        return rewards.sum()

    value_and_grad = jax.jit(jax.value_and_grad(episode_return))
    actions = _episode_actions(env, jax.random.PRNGKey(3))
    ret, g = value_and_grad(actions)
    g = np.asarray(g)
    assert np.isfinite(float(ret)) and 0 <= float(ret) <= HORIZON
    assert g.shape == actions.shape and np.all(np.isfinite(g)), g
    assert np.abs(g).max() > 0
    # the reverse-mode derivative matches a central difference (float32)
    v = np.array(jax.random.normal(jax.random.PRNGKey(4), actions.shape))
    v /= np.linalg.norm(v)
    eps = 1e-2
    fd = (float(value_and_grad(actions + eps * v)[0])
          - float(value_and_grad(actions - eps * v)[0])) / (2 * eps)
    np.testing.assert_allclose(float(np.sum(g * v)), fd, rtol=5e-2, atol=1e-3)


def test_overrides_make_a_new_config_and_name_bad_fields():
    env = envs.make("cartpole_swingup", episode_length=100, reset_angle_noise=0.0)
    assert env.config.episode_length == 100 and env.config.swingup
    assert envs.default_config("cartpole_swingup").episode_length == 250  # defaults untouched
    with pytest.raises(dataclasses.FrozenInstanceError):
        env.config.episode_length = 3
    with pytest.raises(TypeError, match="episode_lenght"):
        envs.make("push", episode_lenght=10)
    with pytest.raises(ValueError, match="no_such_task"):
        envs.make("no_such_task")
    with pytest.raises(ValueError, match="episode_length"):
        envs.make("push", episode_length=0)
    env = envs.make("pendulum_swingup")  # an action of the wrong size is named, not reshaped
    with pytest.raises(ValueError, match=r"pendulum_swingup: action has shape \(3,\); the task "
                                         r"takes \(1,\)"):
        env.step(env.reset(jax.random.key(0)), np.zeros(3))


def test_every_config_field_has_a_docstring():
    import inspect
    for name in NAMES:
        cls = type(envs.default_config(name))
        src = "".join(inspect.getsource(c) for c in cls.__mro__ if c.__module__.startswith("twinrl"))
        for f in dataclasses.fields(cls):
            assert f'{f.name}:' in src and '"""' in src.split(f"{f.name}:", 1)[1].split("\n", 2)[1], (
                name, f.name)


def test_task_declares_cameras_and_action_bounds(made):
    for name, env in made.items():
        m = env.sim.mj_model
        for cam in env.cameras:
            assert m.camera(cam).id >= 0
        s = env.reset(jax.random.PRNGKey(0))
        q, v = s.pipeline_state.qpos, s.pipeline_state.qvel
        big, one = jnp.full(env.action_size, 2.0), jnp.ones(env.action_size)
        ctrl = np.asarray(env.control(q, v, big))
        np.testing.assert_array_equal(ctrl, env.control(q, v, one))  # actions clip to [-1, 1]
        r = env.sim.ctrl_range
        assert ctrl.shape == (env.sim.nu,) and np.all((ctrl >= r[:, 0]) & (ctrl <= r[:, 1]))
        if type(env).control is envs.Env.control:  # affine onto the actuators' range
            np.testing.assert_array_equal(ctrl, r[:, 1])
        assert env.episode_length > 0 and env.dt > 0 and env.backend == "mjx"


def test_params_with_new_dry_friction_get_a_friction_row():
    # MJX fixes friction-loss rows at put_model: identified rail friction (absent from the MJCF)
    # must reach the compiled model, or it would silently do nothing in the simulator.
    nominal = envs.make("cartpole_balance")
    p = nominal.sim.default_params()
    rough = envs.make("cartpole_balance",
                      params=p.replace(frictionloss=p.frictionloss.at[0].set(2.0)))
    assert nominal.sim.mj_model.dof_frictionloss[0] == 0
    assert rough.sim.mj_model.dof_frictionloss[0] == 2.0
    push = jnp.array([0.1])                           # 1 N, below the 2 N of dry friction
    moved = []
    for env in (nominal, rough):
        s = env.reset(jax.random.key(0))
        s = s.replace(pipeline_state=env.sim.init(jnp.zeros(2), jnp.zeros(2)))
        moved.append(abs(float(jax.jit(env.step)(s, push).pipeline_state.qvel[0])))
    assert moved[0] > 1e-2 and moved[1] < moved[0] / 10, moved  # (MJX friction is soft)


def test_observes_state_says_where_sysid_can_start_from_observations():
    """Real2Sim's windows start from recorded observations: push's task observation (planar)
    cannot give them, its full-state observation and a user's MJCF task can."""
    assert not envs.make("push").observes_state
    assert envs.make("push", observation="state").observes_state
    assert envs.make("cartpole_swingup").observes_state
    assert envs.from_mjcf("<mujoco><worldbody><body><joint type='slide'/><geom size='.1'/>"
                          "</body></worldbody></mujoco>").observes_state
