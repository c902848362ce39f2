"""The DeepMind Control Suite tasks (``envs.dmc``): the wheel's models, dm_control's own rewards
on the same MuJoCo C states, the suite's reset distributions, and Gymnasium-valid real twins.

Compiles are the cost: each task jits its reward once (vmapped over every state) and its real
twin's functions once; the states come from dm_control's own environments on MuJoCo C.
"""

import os
import warnings
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from gymnasium.utils.env_checker import check_env  # noqa: E402

from twinrl import envs  # noqa: E402
from twinrl.envs import dmc  # noqa: E402
from twinrl.real import make_real  # noqa: E402

with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # glfw: no X display (dm_control imports its renderer)
    from dm_control import suite  # noqa: E402
    from dm_control.utils import rewards  # noqa: E402

NAMES = envs.names("dmc")
REQUIRED = ("dmc/cartpole-swingup", "dmc/pendulum-swingup", "dmc/reacher-easy",
            "dmc/finger-spin", "dmc/cheetah-run", "dmc/walker-walk")
EPISODES, STEPS, PROBES = 2, 12, 12
TOL = 1e-5  # float32 rewards against dm_control's float64 (measured: <= 2e-7)


def _probe(domain, qpos, qvel, rng):
    """A state moved into the part of the reward random actions rarely reach (upright, spinning,
    running), so the sparse and thresholded rewards are compared where they are not 0."""
    qpos, qvel = qpos.copy(), qvel.copy()
    if domain == "pendulum":
        qpos[0] = rng.uniform(-0.3, 0.3)
    elif domain == "finger":
        qvel[2] = rng.uniform(-30.0, 0.0)
    elif domain == "cheetah":
        qvel[0] = rng.uniform(0.0, 25.0)
    elif domain == "walker":
        qpos[0] = rng.uniform(-0.3, 0.3)  # rootz: torso height about 1.3 m
        qvel[1] = rng.uniform(0.0, 3.0)  # rootx
    return qpos, qvel


def _suite_states(name):
    """(qpos, qvel, action, dm_control's reward) from the suite's own initial states and random
    actions on MuJoCo C, then probes (``_probe``) rewarded by ``task.get_reward(physics)``."""
    domain, task = name.removeprefix("dmc/").split("-")
    rng = np.random.default_rng(0)
    rows = []
    for ep in range(EPISODES):
        env = suite.load(domain, task, task_kwargs={"random": ep})
        env.reset()
        spec = env.action_spec()
        ph = env.physics
        target = ph.named.model.geom_pos["target", :2].copy() if domain == "reacher" else ()
        for _ in range(STEPS):
            a = rng.uniform(spec.minimum, spec.maximum)
            r = env.step(a).reward
            rows.append((np.concatenate([ph.data.qpos, target]), ph.data.qvel.copy(), a, r))
        for _ in range(PROBES // EPISODES):
            q, v, a, _ = rows[rng.integers(len(rows))]
            q, v = _probe(domain, q[:ph.model.nq], v, rng)
            with ph.reset_context():
                ph.data.qpos[:], ph.data.qvel[:], ph.data.ctrl[:] = q, v, a
            if domain == "reacher":  # the target moved to within 8 cm of the finger
                target = ph.named.data.geom_xpos["finger", :2] + rng.uniform(-0.08, 0.08, 2)
                ph.named.model.geom_pos["target", :2] = target
                ph.forward()
            rows.append((np.concatenate([q, target]), v, a, env.task.get_reward(ph)))
    return [np.asarray(x, np.float32) for x in zip(*rows)]


def test_the_control_suite_tasks_are_registered():
    assert set(REQUIRED) <= set(NAMES)
    assert set(NAMES) | set(envs.names("twinrl")) == set(envs.names())
    assert not set(NAMES) & set(envs.names("twinrl"))
    with pytest.raises(ValueError, match="suite"):
        envs.names("gym")


def test_the_models_are_the_wheels_own():
    import dm_control

    folder = dmc.suite_dir()
    assert folder.parent == Path(dm_control.__file__).parent
    xml = dmc.suite_xml("cartpole")
    assert "<include" not in xml and "skybox" in xml  # the common assets inlined
    assert 'energy="enable"' not in xml and "<sensor" not in dmc.suite_xml("walker")
    env = envs.make("dmc/walker-walk")
    assert env.dt == pytest.approx(0.025) and env.episode_length == 1000


@pytest.mark.parametrize("sigmoid,vam", [("gaussian", 0.1), ("linear", 0.0), ("linear", 0.5),
                                         ("quadratic", 0.0), ("hyperbolic", 0.1),
                                         ("long_tail", 0.1), ("cosine", 0.1),
                                         ("reciprocal", 0.1), ("tanh_squared", 0.1)])
def test_tolerance_is_dm_controls(sigmoid, vam):
    x = np.linspace(-4, 6, 101)
    for bounds, margin in (((0.0, 0.0), 2.0), ((1.0, np.inf), 1.5), ((-1.0, 2.0), 0.0)):
        ours = np.asarray(dmc.tolerance(jnp.asarray(x), bounds, margin, sigmoid, vam))
        theirs = rewards.tolerance(x, bounds, margin, sigmoid, vam)
        np.testing.assert_allclose(ours, theirs, atol=1e-6)
    # an infinite bound leaves the gradient finite (a where-branch of x - inf would not)
    g = jax.grad(lambda v: dmc.tolerance(v, (1.0, np.inf), 1.0, sigmoid, vam))
    assert np.isfinite(np.asarray([g(v) for v in (0.5, 2.0)])).all()


@pytest.mark.parametrize("name", NAMES)
def test_reward_equals_dm_controls(name):
    qpos, qvel, action, expected = _suite_states(name)
    env = envs.make(name)
    ours = np.asarray(jax.jit(jax.vmap(lambda q, v, a: env.reward(q, v, a)[0]))(
        qpos, qvel, action))
    diff = np.abs(ours - expected).max()
    print(f"{name}: {len(expected)} states, max |reward - dm_control's| = {diff:.2g}")
    assert diff <= TOL, (name, diff)
    assert 0 < np.mean(expected > 0), f"{name}: no state is rewarded; the test compares zeros"


def test_reset_distributions_are_the_suites():
    keys = jax.random.split(jax.random.PRNGKey(0), 256)
    swing = envs.make("dmc/cartpole-swingup")
    q, v = jax.vmap(swing.initial_state)(keys)
    assert np.abs(np.asarray(q[:, 1]) - np.pi).max() < 0.06 and np.abs(np.asarray(v)).max() < 0.06
    pend = envs.make("dmc/pendulum-swingup")
    q, _ = jax.vmap(pend.initial_state)(keys)
    assert np.asarray(q).min() < -2.5 and np.asarray(q).max() > 2.5  # uniform in [-pi, pi)
    reacher = envs.make("dmc/reacher-easy")
    q, _ = jax.vmap(reacher.initial_state)(keys)
    radius = np.linalg.norm(np.asarray(q[:, 2:4]), axis=1)
    assert radius.min() >= 0.05 - 1e-6 and radius.max() <= 0.2 + 1e-6
    assert np.abs(np.asarray(q[:, 1])).max() <= np.deg2rad(160) + 1e-6


@pytest.mark.parametrize("name", REQUIRED)
def test_real_twin_passes_check_env(name):
    twin = make_real(name, seed=0)
    with warnings.catch_warnings():
        # unbounded observation boxes are deliberate (velocities); gymnasium only warns about it
        warnings.filterwarnings("ignore", message=".*Box observation space m.*infinity")
        check_env(twin, skip_render_check=True)
    obs, _ = twin.reset(seed=1)
    _, r, terminated, truncated, info = twin.step(np.zeros(twin.action_space.shape, np.float32))
    assert obs.shape == twin.observation_space.shape and 0 <= r <= 1 and not terminated
    assert set(info) == {f"reward/{k}" for k in twin.task.reward_term_names}


def test_every_config_field_has_a_docstring():
    import dataclasses
    import inspect

    for name in NAMES:
        cls = type(envs.default_config(name))
        src = "".join(inspect.getsource(c) for c in cls.__mro__
                      if c.__module__.startswith("twinrl"))
        for f in dataclasses.fields(cls):
            after = src.split(f"{f.name}:", 1)
            assert len(after) == 2 and '"""' in after[1].split("\n", 2)[1], (name, f.name)


@pytest.mark.parametrize("name", ["dmc/cartpole-swingup", "dmc/walker-walk"])
def test_the_simulator_steps_as_dm_control(name):
    # same state, same actions: the task's Brax step (MJX; RK4 for the cartpole, 10 substeps
    # with contacts for the walker) against dm_control's MuJoCo C, control step by control step
    domain, task = name.removeprefix("dmc/").split("-")
    de = suite.load(domain, task, task_kwargs={"random": 0})
    de.reset()
    ph = de.physics
    q0, v0 = ph.data.qpos.copy(), ph.data.qvel.copy()
    actions = np.random.default_rng(0).uniform(-1, 1, (10, ph.model.nu)).astype(np.float32)
    theirs = []
    for a in actions:
        de.step(a)
        theirs.append(ph.data.qpos.copy())
    env = envs.make(name)
    state = env.reset(jax.random.PRNGKey(0))
    state = state.replace(pipeline_state=env.sim.init(jnp.asarray(q0, jnp.float32),
                                                      jnp.asarray(v0, jnp.float32)))

    def step(s, a):
        s = env.step(s, a)
        return s, (s.pipeline_state.qpos, s.obs, s.reward)

    _, (ours, obs, rewards) = jax.jit(lambda s, A: jax.lax.scan(step, s, A))(
        state, jnp.asarray(actions))
    assert obs.shape == (10, env.observation_size) and obs.dtype == jnp.float32
    assert np.all((np.asarray(rewards) >= 0) & (np.asarray(rewards) <= 1))
    err = np.abs(np.asarray(ours) - np.asarray(theirs)).max()
    print(f"{name}: max |qpos - dm_control's| over 10 control steps = {err:.2g}")
    assert err < 1e-4, err  # measured: 3e-7 (cartpole), 4e-6 (walker, contacts)


SMOOTH = {"dmc/cartpole-swingup", "dmc/cartpole-balance", "dmc/cheetah-run", "dmc/walker-walk"}
MARGIN = {"dmc/pendulum-swingup": 0.5, "dmc/reacher-easy": 0.3, "dmc/finger-spin": 15.0}
"""``reward_margin`` of the sparse tasks, in their units (cos, m, rad/s)."""


@pytest.mark.parametrize("name", NAMES)
def test_rewards_are_differentiable_where_the_suites_are_smooth(name):
    # the gradient w.r.t. the state is finite everywhere (infinite bounds included) and not zero
    # for the smooth rewards; the sparse ones get one from reward_margin > 0
    qpos, qvel, action, _ = _suite_states(name)
    env = envs.make(name, **({} if name in SMOOTH else {"reward_margin": MARGIN[name]}))
    grad = jax.jit(jax.vmap(jax.grad(lambda q, v, a: env.reward(q, v, a)[0], argnums=(0, 1))))
    gq, gv = (np.asarray(g) for g in grad(qpos, qvel, action))
    assert np.isfinite(gq).all() and np.isfinite(gv).all(), name
    assert np.abs(np.concatenate([gq, gv], 1)).max(axis=1).mean() > 0, name


def test_finger_resets_without_interpenetration_as_the_suite_checks():
    # the reset keeps the first draw whose geoms do not interpenetrate: twinrl's test of that
    # agrees with MuJoCo C's contact count (ncon > 0) on the suite's own random draws
    from dm_control.suite.utils import randomizers

    physics = suite.load("finger", "spin", task_kwargs={"random": 0}).physics
    rng = np.random.RandomState(1)
    qpos, touching = [], []
    for _ in range(60):
        randomizers.randomize_limited_and_rotational_joints(physics, rng)
        physics.after_reset()
        qpos.append(physics.data.qpos.copy())
        touching.append(physics.data.ncon > 0)
    env = envs.make("dmc/finger-spin")
    ours = np.asarray(jax.jit(jax.vmap(env.penetrating))(jnp.asarray(np.array(qpos), jnp.float32)))
    assert any(touching) and not all(touching)
    np.testing.assert_array_equal(ours, np.array(touching))
