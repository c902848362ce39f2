"""``System`` (the identified twin as one value): exact JSON round trip, ``envs.make(system=...)``,
the latency wrapper (delay, gradients through the queue, Brax's auto-reset), and Brax-style
domain randomisation. The pendulum keeps the compiles small."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs.wrappers import training as brax_training

from twinrl import envs
from twinrl.envs import LatencyWrapper, System, randomization_fn, system_of
from twinrl.envs.system import SystemFormatError

TASK = "pendulum_swingup"


def _leaves_equal(a, b):
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype == np.float64 and x.shape == y.shape
        np.testing.assert_array_equal(x, y)


@pytest.fixture(scope="module")
def identified():
    """A system unlike the nominal one: every parameter moved by a float64 factor that float32
    cannot hold, two steps of latency, a camera and an object."""
    nom = System.nominal(TASK, cameras=True)
    rng = np.random.default_rng(0)
    p = nom.params
    params = p.replace(**{k: np.asarray(v) * (1 + rng.uniform(0.01, 0.3, np.shape(v)) / 3)
                          for k, v in p.as_dict().items() if k in ("mass", "damping", "gain")})
    return nom.replace(params=params, latency=2,
                       objects={"ball": {"pos": np.array([0.1, 1 / 3, np.pi]),
                                         "rgba": np.array([0.2, 0.4, 0.6, 1.0])}})


def test_json_round_trip_is_exact_in_float64(identified, tmp_path):
    doc = json.loads(json.dumps(identified.to_json()))          # through text, as on disk
    back = System.from_json(doc)
    assert back.latency == 2 and back.task == TASK
    assert back.cameras["front"].width == 64 and back.cameras["front"].principal is None
    _leaves_equal(identified, back)
    assert back.to_json() == identified.to_json()
    identified.save(tmp_path)
    _leaves_equal(identified, System.load(tmp_path / "system.json"))
    with pytest.raises(SystemFormatError, match="format"):
        System.from_json({**doc, "format": "other"})
    with pytest.raises(SystemFormatError, match="params"):
        System.from_json({k: v for k, v in doc.items() if k != "params"})


def test_system_is_a_pytree_with_static_latency(identified):
    out = jax.jit(lambda s: jax.tree.map(lambda x: 2 * x, s))(identified)
    assert isinstance(out, System) and out.latency == 2 and out.task == TASK
    np.testing.assert_allclose(out.params.mass, 2 * identified.params.mass, rtol=1e-6)
    with pytest.raises(ValueError, match="latency"):
        System(params=identified.params, latency=-1)
    with pytest.raises(ValueError, match="registered"):
        System(params=identified.params, task="nope")


def test_make_builds_the_system(identified):
    env = envs.make(TASK, system=identified)
    assert isinstance(env, LatencyWrapper) and env.latency == 2
    assert env.sys is identified and env.unwrapped is env
    np.testing.assert_array_equal(env.env.params.mass, identified.params.mass)
    assert system_of(env) is identified
    assert not isinstance(envs.make(TASK, system=identified.replace(latency=0)), LatencyWrapper)
    plain = system_of(envs.make(TASK))                      # a bare task: its MJCF, no delay
    assert plain.latency == 0 and plain.task == TASK
    _leaves_equal(plain.params, System.nominal(TASK).params)
    with pytest.raises(ValueError, match="not both"):
        envs.make(TASK, system=identified, params=identified.params)
    with pytest.raises(ValueError, match="cartpole_swingup"):
        envs.make("cartpole_swingup", system=identified)


def _qpos_trajectory(env, state, actions):
    def body(s, a):
        s = env.step(s, a)
        return s, s.pipeline_state.qpos
    return jax.lax.scan(body, state, actions)[1]


def test_latency_delays_actions_and_gradients_go_through_the_queue():
    base = System.nominal(TASK)
    delayed = envs.make(TASK, system=base.replace(latency=2))
    bare = envs.make(TASK, system=base)
    s0 = bare.reset(jax.random.key(0))
    d0 = delayed.reset(jax.random.key(0))
    actions = jnp.asarray(np.random.default_rng(1).uniform(-1, 1, (12, 1)), jnp.float32)
    shifted = jnp.concatenate([jnp.zeros((2, 1)), actions[:-2]])
    q_delayed = jax.jit(_qpos_trajectory, static_argnums=0)(delayed, d0, actions)
    q_bare = jax.jit(_qpos_trajectory, static_argnums=0)(bare, s0, shifted)
    np.testing.assert_array_equal(np.asarray(q_delayed), np.asarray(q_bare))
    assert not np.allclose(q_delayed, jax.jit(_qpos_trajectory, static_argnums=0)(
        bare, s0, actions), atol=1e-4)
    # the final angle depends on the actions sent 2 or more steps before the end, not after
    grad = jax.jit(jax.grad(lambda a: _qpos_trajectory(delayed, d0, a)[-1].sum()))(actions)
    grad = np.asarray(grad)
    assert np.all(np.isfinite(grad))
    assert np.all(grad[-2:] == 0) and np.all(grad[:-2] != 0)
    # vmap over start states: each keeps its own queue
    batch = jax.vmap(delayed.reset)(jax.random.split(jax.random.key(2), 3))
    out = jax.jit(jax.vmap(delayed.step))(batch, jnp.ones((3, 1)))
    assert out.info["latency/queue"].shape == (3, 2, 1)
    np.testing.assert_array_equal(out.info["latency/queue"][:, -1], 1.0)


def test_brax_auto_reset_empties_the_queue():
    env = envs.make(TASK, system=System.nominal(TASK).replace(latency=1))
    wrapped = brax_training.wrap(env, episode_length=3)
    state = jax.jit(wrapped.reset)(jax.random.split(jax.random.PRNGKey(0), 1))  # raw keys, as Brax
    step = jax.jit(wrapped.step)
    first = None
    for t in range(4):
        state = step(state, jnp.ones((1, 1)))
        if t == 0:
            first = np.asarray(state.pipeline_state.qpos)
    # step 3 starts a new episode from the reset state: its applied action is the empty queue's
    # zero, as in step 0, not the previous episode's last action
    np.testing.assert_array_equal(np.asarray(state.pipeline_state.qpos), first)


def test_randomization_fn_batches_masses_and_frictions(identified):
    keys = jax.random.split(jax.random.key(0), 4)
    batch, in_axes = randomization_fn(identified, keys, mass_scale=(0.5, 2.0))
    p, q = identified.params, batch.params
    assert q.mass.shape == (4,) + np.shape(p.mass) and q.damping.shape == (4,) + np.shape(p.damping)
    ratio = np.asarray(q.mass) / np.asarray(p.mass)
    assert np.all((ratio >= 0.5) & (ratio <= 2.0)) and np.ptp(ratio) > 0.05
    np.testing.assert_allclose(q.damping, np.broadcast_to(p.damping, q.damping.shape), rtol=1e-6)
    assert batch.latency == 2 and in_axes.params.mass == 0 and in_axes.cameras["front"].pos is None
    with pytest.raises(TypeError, match="System"):
        randomization_fn(None, keys)
    # Brax's own domain-randomisation wrapper steps the delayed, randomised systems
    env = envs.make(TASK, system=identified.replace(cameras=None, objects=None))
    dr = brax_training.DomainRandomizationVmapWrapper(
        env, lambda s: randomization_fn(s, keys, mass_scale=(0.5, 2.0)))
    s = jax.jit(dr.reset)(jnp.stack([jax.random.PRNGKey(0)] * 4))
    for _ in range(3):
        s = jax.jit(dr.step)(s, jnp.ones((4, 1)))
    qvel = np.asarray(s.pipeline_state.qvel)[:, 0]
    assert np.ptp(qvel) > 1e-4                 # same start, same actions, other masses
    assert s.info["latency/queue"].shape == (4, 2, 1)
    assert env.env.params is identified.params  # restored after the randomised step


def test_brax_ppo_trains_on_the_delayed_env_unmodified():
    from twinrl.learn import baselines
    from twinrl.learn.baselines import PPOConfig

    env = envs.make(TASK, system=System.nominal(TASK).replace(latency=1))
    tiny = PPOConfig(num_timesteps=1024, num_envs=8, batch_size=8, num_minibatches=4,
                     unroll_length=8, num_updates_per_batch=1, policy_hidden=(8,),
                     value_hidden=(8,), num_evals=2, num_eval_envs=2, episode_length=16)
    policy, params, metrics = baselines.ppo_train(env, tiny, jax.random.PRNGKey(0))
    assert len(metrics["return"]) == 2 and np.all(np.isfinite(metrics["return"]))
    a = policy.apply(params, jnp.zeros(env.observation_size))
    assert a.shape == (1,) and bool(jnp.all(jnp.abs(a) <= 1))


def test_tool_and_controller_are_typed_and_keep_the_files_layout():
    # The tool's grasp and the controller's calibration are typed records on a System; on disk
    # they stay the "objects" entries files have always had, and a System built with such entries
    # (an older file, or objects=...) reads them as the records.
    from twinrl.envs.system import ControllerCalibration, ToolGrasp

    nom = System.nominal(TASK)
    grasp = ToolGrasp(pos_offset=np.array([0.004, -1 / 3, np.pi]), rot_offset=[0.1, 0.0, -0.2])
    calibration = ControllerCalibration(joint_speed=np.array([1.1, 1 / 7]))
    s = nom.replace(tool=grasp, controller=calibration,
                    objects={"ball": {"pos": np.array([0.1, 0.2, 0.3])}})
    doc = json.loads(json.dumps(s.to_json()))
    assert sorted(doc["objects"]) == ["ball", "controller", "tool"]
    assert doc["objects"]["tool"] == {"pos_offset": [0.004, -1 / 3, np.pi],
                                      "rot_offset": [0.1, 0.0, -0.2]}
    assert doc["objects"]["controller"] == {"joint_speed": [1.1, 1 / 7]}
    back = System.from_json(doc)
    assert isinstance(back.tool, ToolGrasp) and isinstance(back.controller, ControllerCalibration)
    assert sorted(back.objects) == ["ball"]
    _leaves_equal(s, back)
    assert back.to_json() == s.to_json()
    legacy = nom.replace(objects={"tool": {"pos_offset": [0.004, -1 / 3, np.pi],
                                           "rot_offset": [0.1, 0.0, -0.2]}})
    assert legacy.objects is None and isinstance(legacy.tool, ToolGrasp)
    _leaves_equal(legacy.tool, grasp)
    assert legacy.to_json()["objects"] == {"tool": doc["objects"]["tool"]}
    assert nom.to_json()["objects"] is None
    out = jax.jit(lambda s: jax.tree.map(lambda x: 2 * x, s))(s)  # the records are pytree nodes
    assert isinstance(out.tool, ToolGrasp)
    np.testing.assert_allclose(out.controller.joint_speed, 2 * calibration.joint_speed, rtol=1e-6)
    with pytest.raises(ValueError, match="tool given twice"):
        s.replace(objects={"tool": doc["objects"]["tool"]})
    with pytest.raises(ValueError, match="ToolGrasp.pos_offset must be 3 numbers"):
        ToolGrasp([0.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="rot_offset"):
        nom.replace(tool={"pos_offset": [0.0, 0.0, 0.0]})


def test_with_system_returns_a_new_task(identified):
    bare = envs.make(TASK)
    new = bare.with_system(identified)
    assert new is not bare and new.sys is identified and bare.sys is None and bare.params is None
    np.testing.assert_array_equal(new.params.mass, identified.params.mass)
    delayed = envs.make(TASK, system=identified)
    again = delayed.with_system(identified.replace(latency=1))
    assert isinstance(again, LatencyWrapper) and again.latency == 1 and delayed.latency == 2
    assert again.env is not delayed.env and delayed.env.sys is identified
    assert not isinstance(delayed.with_system(identified.replace(latency=0)), LatencyWrapper)
