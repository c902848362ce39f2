"""``twinrl.learn.trajopt``: exactness on a linear-quadratic problem (any action dimension), monotone
improvement on a real task (cartpole swing-up), and the non-finite guard.

Compiles dominate: each MJX test jits one ``optimize`` (a ``lax.scan`` of a few steps) per order,
with short horizons, on cartpole (no joint limit, so no constraint solve in the compiled gradient).
The Gauss-Newton step with a 2-D action through contacts is exercised on ``push`` by
``tests/learn/test_pods.py::test_second_order_on_push_with_a_2d_action`` (PODS calls
``trajopt.improve``), so it is not compiled a second time here.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs
from twinrl.learn import trajopt
from twinrl.learn.trajopt import TrajoptConfig, env_problem, improve, optimize

# ----------------------------------------------------------------------------- linear-quadratic
T_LQ, N_LQ, M_LQ = 6, 3, 2


def _lq():
    rng = np.random.default_rng(0)
    A = np.eye(N_LQ) + 0.1 * rng.standard_normal((N_LQ, N_LQ))
    B = 0.5 * rng.standard_normal((N_LQ, M_LQ))
    Q = np.diag([1.0, 0.5, 2.0])
    R = np.diag([0.3, 0.1])
    s0 = np.array([0.4, -0.3, 0.2])
    return A, B, Q, R, s0


def _lq_problem(nan_reward=False):
    A, B, Q, R, s0 = (jnp.asarray(x) for x in _lq())

    def rollout_fn(actions):
        def body(s, a):
            s = A @ s + B @ a
            return s, s
        return jax.lax.scan(body, s0.astype(actions.dtype), actions)[1]

    def reward_fn(s, a):
        r = -(s @ Q @ s + a @ R @ a)
        if nan_reward:
            # finite value, NaN gradient: d sqrt(x)/dx = inf at 0, times d(0 * s)/ds = 0
            r = r - jnp.sqrt(0.0 * s[0])
        return r

    return rollout_fn, reward_fn


def _lq_optimum(gamma=1.0, terminal=None):
    """Closed form: s = S0 + G a, so V = -(s'Qs + a'Ra) is maximised by
    (G'QG + R) a = -G'Q S0 over the stacked sequences; with a discount the blocks of Q and R are
    weighted by gamma^t, and a terminal value -s'Ps adds gamma^T P to the last state's block."""
    A, B, Q, R, s0 = _lq()
    G = np.zeros((T_LQ * N_LQ, T_LQ * M_LQ))
    S0 = np.zeros(T_LQ * N_LQ)
    for t in range(T_LQ):
        S0[t * N_LQ:(t + 1) * N_LQ] = np.linalg.matrix_power(A, t + 1) @ s0
        for k in range(t + 1):
            G[t * N_LQ:(t + 1) * N_LQ, k * M_LQ:(k + 1) * M_LQ] = (
                np.linalg.matrix_power(A, t - k) @ B)
    w = gamma ** np.arange(T_LQ)
    Qb = np.kron(np.diag(w), Q)
    if terminal is not None:
        Qb[-N_LQ:, -N_LQ:] += gamma ** T_LQ * terminal
    Rb = np.kron(np.diag(w), R)
    a = np.linalg.solve(G.T @ Qb @ G + Rb, -G.T @ Qb @ S0)
    s = S0 + G @ a
    return a.reshape(T_LQ, M_LQ), -(s @ Qb @ s + a @ Rb @ a)


def test_gauss_newton_full_step_reaches_the_lq_optimum():
    a_star, v_star = _lq_optimum()
    assert np.abs(a_star).max() < 1.0  # inside the bounds, so clipping plays no part
    with jax.enable_x64(True):
        rollout_fn, reward_fn = _lq_problem()
        cfg = TrajoptConfig(order=2, step_size=1.0, line_search_steps=4, regularization=1e-9)
        a0 = jnp.zeros((T_LQ, M_LQ), jnp.float64)
        res = jax.jit(lambda a: improve(rollout_fn, reward_fn, a, cfg))(a0)
        assert bool(res.accepted)
        assert float(res.alpha) == 1.0  # the full Gauss-Newton step is the best on the line
        np.testing.assert_allclose(res.actions, a_star, atol=1e-6)
        np.testing.assert_allclose(res.value, v_star, rtol=1e-9)
        assert int(res.env_steps) == T_LQ * (1 + 4)
        assert int(res.nonfinite) == 0


def test_first_order_improves_monotonically_towards_the_lq_optimum():
    a_star, v_star = _lq_optimum()
    with jax.enable_x64(True):
        rollout_fn, reward_fn = _lq_problem()
        cfg = TrajoptConfig(order=1, step_size=0.5, line_search_steps=6)
        a0 = jnp.full((T_LQ, M_LQ), 0.5, jnp.float64)
        v0 = float(trajopt.trajectory_return(rollout_fn, reward_fn, a0))
        a, hist = jax.jit(lambda a: optimize(rollout_fn, reward_fn, a, cfg, 30))(a0)
    values = np.concatenate([[v0], np.asarray(hist.value)])
    assert np.all(np.diff(values) >= 0), values
    assert np.all(np.asarray(hist.accepted)[:5])  # far from the optimum every step improves
    np.testing.assert_allclose(np.asarray(hist.old_value)[1:], np.asarray(hist.value)[:-1])
    assert v_star - values[-1] < 0.05 * (v_star - v0)
    assert values[-1] <= v_star + 1e-12


GAMMA = 0.9
P_TERM = np.diag([3.0, 1.0, 0.5])


def _terminal_fn(s):
    return -(s @ jnp.asarray(P_TERM, s.dtype) @ s)


def test_discount_and_terminal_value():
    a_star, v_star = _lq_optimum(GAMMA, P_TERM)
    with jax.enable_x64(True):
        rollout_fn, reward_fn = _lq_problem()
        a0 = jnp.zeros((T_LQ, M_LQ), jnp.float64)
        # the objective is the hand-written one
        a1 = jnp.asarray(np.random.default_rng(1).uniform(-0.5, 0.5, (T_LQ, M_LQ)))
        states = rollout_fn(a1)
        manual = sum(GAMMA ** t * reward_fn(states[t], a1[t]) for t in range(T_LQ))
        manual = manual + GAMMA ** T_LQ * _terminal_fn(states[-1])
        v = trajopt.trajectory_return(rollout_fn, reward_fn, a1, GAMMA, _terminal_fn)
        np.testing.assert_allclose(v, manual, rtol=1e-12)
        # with the terminal value's curvature the full Gauss-Newton step solves the LQ problem
        cfg = TrajoptConfig(order=2, step_size=1.0, line_search_steps=4, regularization=1e-9,
                            discount=GAMMA, terminal_curvature=True)
        res = jax.jit(lambda a: improve(rollout_fn, reward_fn, a, cfg, _terminal_fn))(a0)
        assert bool(res.accepted) and float(res.alpha) == 1.0
        np.testing.assert_allclose(res.actions, a_star, atol=1e-6)
        np.testing.assert_allclose(res.value, v_star, rtol=1e-9)
        # without it (the default: a learned critic enters linearly) the step still ascends,
        # and first-order steps climb towards the same optimum
        cfg_lin = TrajoptConfig(order=2, regularization=1e-9, discount=GAMMA)
        lin = jax.jit(lambda a: improve(rollout_fn, reward_fn, a, cfg_lin, _terminal_fn))(a0)
        assert bool(lin.accepted) and float(lin.value) > float(lin.old_value)
        assert not np.allclose(lin.actions, a_star, atol=1e-3)
        cfg1 = TrajoptConfig(order=1, step_size=0.5, line_search_steps=6, discount=GAMMA)
        _, hist = jax.jit(lambda a: optimize(rollout_fn, reward_fn, a, cfg1, 40, _terminal_fn))(
            a0 + 0.5)
        v0 = float(trajopt.trajectory_return(rollout_fn, reward_fn, a0 + 0.5, GAMMA, _terminal_fn))
        values = np.concatenate([[v0], np.asarray(hist.value)])
        assert np.all(np.diff(values) >= 0)
        assert v_star - values[-1] < 0.05 * (v_star - v0)


def test_max_step_norm_and_direction_scale():
    with jax.enable_x64(True):
        rollout_fn, reward_fn = _lq_problem()
        a0 = jnp.full((T_LQ, M_LQ), 0.5, jnp.float64)
        # a trust region: the accepted change is at most step_size * max_step_norm
        cfg = TrajoptConfig(order=2, step_size=1.0, line_search_steps=4, regularization=1e-9,
                            max_step_norm=0.05)
        # each jitted: one compile, not every operation compiled on its own
        res = jax.jit(lambda a: improve(rollout_fn, reward_fn, a, cfg))(a0)
        assert bool(res.accepted)
        np.testing.assert_allclose(float(jnp.linalg.norm(res.actions - a0)), 0.05, rtol=1e-9)
        # direction_scale s with step_size 1 tries exactly step_size s's candidates
        base = TrajoptConfig(order=1, step_size=1.0, line_search_steps=5)
        scaled = jax.jit(lambda a: improve(rollout_fn, reward_fn, a, base,
                                           direction_scale=jnp.float64(0.25)))(a0)
        plain = jax.jit(lambda a: improve(rollout_fn, reward_fn, a, TrajoptConfig(
            order=1, step_size=0.25, line_search_steps=5)))(a0)
        np.testing.assert_allclose(scaled.actions, plain.actions, rtol=1e-12)
        np.testing.assert_allclose(scaled.alpha, plain.alpha, rtol=1e-12)
    for bad, word in [(dict(discount=0.0), "discount"), (dict(discount=1.5), "discount"),
                      (dict(max_step_norm=0.0), "max_step_norm")]:
        with pytest.raises(ValueError, match=word):
            TrajoptConfig(**bad)


@pytest.mark.parametrize("order", [1, 2])
def test_nonfinite_gradient_takes_no_step_and_is_counted(order):
    rollout_fn, reward_fn = _lq_problem(nan_reward=True)
    cfg = TrajoptConfig(order=order)
    a0 = jnp.full((T_LQ, M_LQ), 0.3, jnp.float32)
    _, hist = jax.jit(lambda a: optimize(rollout_fn, reward_fn, a, cfg, 2))(a0)
    assert np.asarray(hist.nonfinite).tolist() == [1, 1]
    assert not np.any(np.asarray(hist.accepted))
    np.testing.assert_array_equal(hist.actions[-1], a0)
    np.testing.assert_array_equal(hist.value, hist.old_value)
    assert np.all(np.isfinite(np.asarray(hist.value)))
    assert not np.all(np.isfinite(np.asarray(hist.grad_norm)))


def test_clipping_bounds_and_config_errors():
    rollout_fn, reward_fn = _lq_problem()
    # a huge step: every candidate leaves [-1, 1] before clipping; from actions of -0.9 the
    # clipped one (every action at a bound) is better, so the step is taken
    cfg = TrajoptConfig(order=1, step_size=1e3, line_search_steps=2, max_grad_norm=1.0)
    res = jax.jit(lambda a: improve(rollout_fn, reward_fn, a, cfg))(
        jnp.full((T_LQ, M_LQ), -0.9))
    acts = np.asarray(res.actions)
    assert bool(res.accepted) and float(res.value) > float(res.old_value)
    np.testing.assert_array_equal(np.abs(acts), 1.0)
    # its value is the return of the clipped actions it returns (by hand), not the candidate's
    states = rollout_fn(jnp.asarray(acts))
    manual = sum(float(reward_fn(states[t], jnp.asarray(acts[t]))) for t in range(T_LQ))
    np.testing.assert_allclose(float(res.value), manual, rtol=1e-5)
    for bad, word in [(dict(order=3), "order"), (dict(step_size=0.0), "step_size"),
                      (dict(line_search_steps=0), "line_search_steps"),
                      (dict(regularization=-1.0), "regularization"),
                      (dict(max_grad_norm=0.0), "max_grad_norm"),
                      (dict(action_low=1.0, action_high=-1.0), "action_low")]:
        with pytest.raises(ValueError, match=word):
            TrajoptConfig(**bad)
    with pytest.raises(ValueError, match="actions must have shape"):
        improve(rollout_fn, reward_fn, jnp.zeros(T_LQ), TrajoptConfig())
    with pytest.raises(ValueError, match="rollout_fn must return"):
        improve(lambda a: rollout_fn(a)[:-1], reward_fn, jnp.zeros((T_LQ, M_LQ)), TrajoptConfig())


# ----------------------------------------------------------------------------- MJX tasks
def _run_task(env, state, a0, cfg, iterations):
    fn = jax.jit(lambda s, a: optimize(*env_problem(env, s), a, cfg, iterations))
    return fn(state, a0)


def _assert_never_worse(hist, v0):
    values = np.concatenate([[v0], np.asarray(hist.value)])
    assert np.all(np.isfinite(values)), values
    assert np.all(np.diff(values) >= 0), values
    # each step starts where the last one ended, and a rejected step keeps the value
    np.testing.assert_allclose(np.asarray(hist.old_value), values[:-1], rtol=1e-5)
    acc = np.asarray(hist.accepted)
    assert np.all(np.asarray(hist.alpha)[~acc] == 0)
    return values


@pytest.fixture(scope="module")
def task():
    env = envs.make("cartpole_swingup")
    state = jax.jit(env.reset)(jax.random.PRNGKey(0))
    a0 = 0.3 * jax.random.uniform(jax.random.PRNGKey(1), (30, env.action_size), minval=-1.0,
                                  maxval=1.0)
    return env, state, a0


def test_env_problem_return_equals_the_env_unroll(task):
    env, state, a0 = task
    v = jax.jit(lambda s, a: trajopt.trajectory_return(*env_problem(env, s), a))(state, a0)
    _, rewards = jax.jit(env.unroll)(state, a0)
    np.testing.assert_allclose(v, rewards.sum(), rtol=1e-5)


@pytest.mark.parametrize("order", [1, 2])
def test_iterations_increase_the_return(order, task):
    env, state, a0 = task
    cfg = TrajoptConfig(order=order, step_size=1.0 if order == 2 else 0.5, line_search_steps=6,
                        regularization=1e-2)
    a, hist = _run_task(env, state, a0, cfg, 4)
    v0 = float(jax.jit(lambda s, a: trajopt.trajectory_return(*env_problem(env, s), a))(state, a0))
    values = _assert_never_worse(hist, v0)
    assert values[-1] > v0 + 1e-3, values
    assert a.shape == a0.shape and np.abs(np.asarray(a)).max() <= 1.0
    assert int(np.asarray(hist.env_steps).sum()) == 4 * 30 * (1 + 6)
    assert not np.any(np.asarray(hist.nonfinite))


@pytest.mark.parametrize("order", [1, 2])
def test_improve_vmaps_over_a_batch_of_sequences(order):
    rollout_fn, reward_fn = _lq_problem()
    cfg = TrajoptConfig(order=order, line_search_steps=3)
    batch = jax.random.uniform(jax.random.PRNGKey(0), (3, T_LQ, M_LQ), minval=-0.5, maxval=0.5)
    step = jax.jit(jax.vmap(lambda a: improve(rollout_fn, reward_fn, a, cfg)))
    res = step(batch)
    assert res.actions.shape == batch.shape and res.value.shape == (3,)
    single = jax.jit(lambda a: improve(rollout_fn, reward_fn, a, cfg))
    for i in range(3):  # the batch is the same as one sequence at a time
        one = single(batch[i])
        np.testing.assert_allclose(res.actions[i], one.actions, rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(res.value[i], one.value, rtol=1e-4)


def test_env_problem_goes_through_the_latency_of_the_system():
    """On a latency-2 System, trajopt's return of an action sequence is the wrapped env's
    ``unroll`` return (from a state whose queue holds sent, not yet applied actions), not the
    undelayed one, and its gradient matches float64 central differences."""
    with jax.enable_x64(True):
        system = envs.System.nominal("pendulum_swingup").replace(latency=2)
        env = envs.make("pendulum_swingup", system=system)
        assert isinstance(env, envs.LatencyWrapper)
        state = env.reset(jax.random.PRNGKey(0))
        state = env.step(env.step(state, jnp.array([0.7])), jnp.array([-0.4]))  # queue != 0
        a0 = 0.5 * jax.random.uniform(jax.random.PRNGKey(1), (8, env.action_size),
                                      jnp.float64, -1.0, 1.0)
        ret = jax.jit(lambda s, a: trajopt.trajectory_return(*env_problem(env, s), a))
        v = ret(state, a0)
        _, rewards = jax.jit(env.unroll)(state, a0)
        np.testing.assert_allclose(v, rewards.sum(), rtol=1e-12)
        _, undelayed = jax.jit(env.env.unroll)(state, a0)
        assert abs(float(undelayed.sum()) - float(v)) > 1e-4   # the delay matters here

        g = np.asarray(jax.jit(jax.grad(lambda a: ret(state, a)))(a0))
        eps, fd = 1e-6, np.zeros_like(g)
        for i in np.ndindex(g.shape):
            e = jnp.zeros_like(a0).at[i].set(eps)
            fd[i] = (float(ret(state, a0 + e)) - float(ret(state, a0 - e))) / (2 * eps)
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-8)
