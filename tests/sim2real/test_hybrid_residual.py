"""Hybrid residual dynamics and the zero-initialised residual policy (twinrl.sim2real)."""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs
from twinrl.learn.networks import make_policy
from twinrl.sim2real import hybrid, residual

T = 60


def _record(env, actions, seeds):
    """Transitions of ``env`` (its own simulator) under open-loop ``actions``, as a dataset."""
    step = jax.jit(env.step)
    obs, act, nxt, ep = [], [], [], []
    for e, s in enumerate(seeds):
        state = env.reset(jax.random.key(s))
        for a in actions[e]:
            s2 = step(state, a)
            obs.append(np.asarray(state.obs)), act.append(a), nxt.append(np.asarray(s2.obs))
            ep.append(e)
            state = s2
    return SimpleNamespace(obs=np.array(obs), action=np.array(act, np.float32),
                           next_obs=np.array(nxt), episode_id=np.array(ep))


@pytest.fixture(scope="module")
def setup():
    nominal = envs.make("cartpole_swingup", episode_length=T)
    # The "real" system: a weaker motor and a heavier pole than the simulator knows.
    p0 = nominal.sim.default_params()
    truth = p0.replace(gain=p0.gain * 0.8, mass=p0.mass.at[-1].multiply(1.5))
    real = envs.make("cartpole_swingup", params=truth, episode_length=T)
    rng = np.random.default_rng(0)
    actions = np.clip(np.cumsum(rng.normal(0, 0.4, (4, T, 1)), 1), -1, 1).astype(np.float32)
    data = _record(real, actions, seeds=range(4))
    fit = hybrid.fit(nominal, data, config=hybrid.HybridConfig(steps=400, eval_every=50),
                     rng=jax.random.key(1))
    return nominal, data, fit


def test_untrained_hybrid_is_the_simulator(setup):
    nominal, data, fit = setup
    zero = fit.model._replace(params=jax.tree.map(jnp.zeros_like, fit.model.params))
    dyn = jax.jit(hybrid.make_dynamics(nominal, zero))
    s = nominal.reset(jax.random.key(3))
    a = jnp.array([0.7])
    np.testing.assert_array_equal(np.asarray(dyn(s, a).obs),
                                  np.asarray(jax.jit(nominal.step)(s, a).obs))


def test_fit_reduces_held_out_one_step_error(setup):
    nominal, data, fit = setup
    sim, hyb = np.array(fit.metrics["sim_val_rmse"]), np.array(fit.metrics["hybrid_val_rmse"])
    assert fit.metrics["val_transitions"] > 0
    # The velocity errors (where the gain and mass gap shows) fall at least 3x on held-out
    # episodes; one_step_errors on all the data agrees.
    assert np.all(hyb[2:] < sim[2:] / 3), (sim, hyb)
    assert np.all(hybrid.one_step_errors(nominal, fit.model, data)[2:]
                  < hybrid.one_step_errors(nominal, None, data)[2:] / 3)


def test_bad_data_is_named(setup):
    nominal, data, _ = setup
    bad = SimpleNamespace(**vars(data))
    bad.obs = data.obs.copy()
    bad.obs[5, 0] = np.nan
    with pytest.raises(ValueError, match=r"obs holds non-finite values at transition\(s\) \[5\]"):
        hybrid.transitions(nominal, bad)
    bad.obs = data.obs[:, :3]
    with pytest.raises(ValueError, match="obs must have shape"):
        hybrid.transitions(nominal, bad)


def test_applied_actions_delay_within_episodes():
    a = np.arange(6, dtype=np.float32)[:, None]
    ep = np.array([0, 0, 0, 1, 1, 1])
    np.testing.assert_array_equal(hybrid.applied_actions(a, ep, 1)[:, 0], [0, 0, 1, 0, 3, 4])


@pytest.fixture(scope="module")
def res_setup(setup):
    nominal, data, fit = setup
    base = make_policy(nominal.observation_size, nominal.action_size, (16,))
    base_params = base.init(jax.random.key(7))
    pol = residual.make_residual(base, base_params, residual.ResidualConfig(hidden=(16,)))
    return nominal, data, fit, pol


def test_first_deployment_is_exactly_the_sim_policy(res_setup):
    _, data, _, pol = res_setup
    p0 = pol.delta.init(jax.random.key(0))
    got = jax.vmap(lambda o: pol.act(p0, o))(data.obs)
    want = jnp.clip(jax.vmap(lambda o: pol.base.apply(pol.base_params, o))(data.obs), -1, 1)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_residual_training_improves_the_hybrid_return_within_bounds(res_setup):
    nominal, data, fit, pol = res_setup
    cfg = residual.ResidualConfig(hidden=(16,), horizon=20, batch_size=16, steps=30,
                                  learning_rate=1e-2)
    dyn = hybrid.make_dynamics(nominal, fit.model)
    p, m = residual.train(nominal, dyn, pol, data.obs, cfg, rng=jax.random.key(2))
    assert m["skipped"] == [0.0] and np.all(np.isfinite(m["grad_norm"]))
    p0 = pol.delta.init(jax.random.key(0))
    before = residual.model_return(nominal, dyn, pol, p0, data.obs[::10], cfg.horizon)
    after = residual.model_return(nominal, dyn, pol, p, data.obs[::10], cfg.horizon)
    assert after > 1.03 * before, (before, after)
    d, _ = jax.vmap(lambda o: pol.correction(p, o))(data.obs)
    assert float(jnp.abs(d).max()) <= cfg.scale + 1e-6 and float(jnp.abs(d).max()) > 0
    with pytest.raises(ValueError, match="start_obs must have shape"):
        residual.train(nominal, None, pol, data.obs[:, :2], cfg)


def test_accept_compares_full_episodes_from_the_task_start(res_setup):
    # A model whose reward is the applied action: a constant delta of +scale raises the return
    # of every episode, -scale lowers it, zero leaves it; the gate must say so, over whole
    # episodes (the env's 60 steps) from the task's own initial states.
    nominal, _, _, pol = res_setup

    def dyn(s, a):
        return nominal.step(s, a).replace(reward=a[0])

    p0 = pol.delta.init(jax.random.key(0))

    def constant(sign):  # all-zero weights, last bias saturating the tanh: delta = sign * scale
        p = jax.tree.map(jnp.zeros_like, p0)
        p["params"]["Dense_1"]["bias"] = jnp.full((1,), 20.0 * sign)
        return p

    ok0, b0, a0 = residual.accept(nominal, dyn, pol, p0, jax.random.key(4), episodes=4)[:3]
    assert ok0 and a0 == b0 and np.isfinite(b0)
    ok_up, b_up, a_up = residual.accept(nominal, dyn, pol, constant(+1), jax.random.key(4),
                                        episodes=4)[:3]
    ok_dn, b_dn, a_dn = residual.accept(nominal, dyn, pol, constant(-1), jax.random.key(4),
                                        episodes=4)[:3]
    assert b_up == b_dn == b0
    assert ok_up and a_up > b0 + 0.1 * T * 0.3  # ~+0.3 a step where the clip leaves room
    assert not ok_dn and a_dn < b0 - 0.1 * T * 0.3
    # A second model of the same system that disagrees (its reward is minus the action): delta
    # must do no harm there either, so the one the first model likes is refused, and the verdict
    # carries both models' returns.
    v = residual.accept(nominal, dyn, pol, constant(+1), jax.random.key(4), episodes=4,
                        reference=lambda s, a: nominal.step(s, a).replace(reward=-a[0]))
    assert not v.accepted and v.after == a_up and v.reference_after < v.reference_before
    v = residual.accept(nominal, dyn, pol, constant(+1), jax.random.key(4), episodes=4,
                        reference=dyn)
    assert v.accepted and v.reference_after == v.after


def test_train_gated_deploys_the_trained_delta_only_when_accepted(res_setup):
    """``train_gated`` (both loops' residual stage): ``train`` from key ``seed``, ``accept``
    from key ``seed + 1`` against ``env.step``; the parameters are exactly the trained ones when
    accepted and exactly zero otherwise, and the metrics carry the verdict."""
    nominal, data, fit, pol = res_setup
    cfg = residual.ResidualConfig(hidden=(16,), horizon=5, batch_size=4, steps=3)
    dyn = hybrid.make_dynamics(nominal, fit.model)
    trained, _ = residual.train(nominal, dyn, pol, data.obs, cfg, jax.random.key(5))
    want = residual.accept(nominal, dyn, pol, trained, jax.random.key(6), reference=nominal.step,
                           tolerance=0.0)
    p, m, v = residual.train_gated(nominal, dyn, pol, data.obs, cfg, seed=5, tolerance=0.0)
    assert v == want
    expect = trained if v.accepted else jax.tree.map(jnp.zeros_like, trained)
    for got, exp in zip(jax.tree.leaves(p), jax.tree.leaves(expect)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(exp))
    assert m["accepted"] == float(v.accepted) and m["model_return_after"] == v.after
    assert m["sim_return_before"] == v.reference_before and np.isfinite(m["objective"])


def test_single_episode_is_stopped_on_its_held_out_last_block(setup):
    """One recorded episode still gets a validation set: its last transitions, which the network
    is not fitted to (early stopping on the training data picked whatever fit it best)."""
    nominal, data, _ = setup
    one = np.asarray(data.episode_id) == 0
    single = SimpleNamespace(obs=data.obs[one], action=data.action[one],
                             next_obs=data.next_obs[one], episode_id=data.episode_id[one])
    n = int(one.sum())
    fit = hybrid.fit(nominal, single, config=hybrid.HybridConfig(steps=50, eval_every=25),
                     rng=jax.random.key(0))
    assert fit.metrics["val_transitions"] == round(0.2 * n)
    assert fit.metrics["train_transitions"] == n - round(0.2 * n)
    assert fit.metrics["val_episodes"] == []
    # two or more episodes: whole episodes are held out, as before
    assert hybrid.fit(nominal, data, config=hybrid.HybridConfig(steps=50, eval_every=25),
                      rng=jax.random.key(0)).metrics["val_episodes"]
