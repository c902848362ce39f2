"""Gradient hygiene transforms: NaN guard, clipping, truncation windows."""

import jax
import jax.numpy as jnp
import numpy as np
import optax

from twinrl.physics import Sim, gradients


def test_nan_guard_zeroes_and_counts_and_params_stay_finite():
    params = {"w": jnp.ones(3), "b": jnp.zeros(2)}
    opt = optax.chain(gradients.hygiene(max_norm=1.0), optax.adam(0.1))
    state = opt.init(params)
    good = {"w": jnp.ones(3), "b": jnp.ones(2)}
    bad = {"w": jnp.array([1.0, jnp.nan, 1.0]), "b": jnp.array([jnp.inf, 0.0])}
    for g in [good, bad, good, bad]:
        updates, state = opt.update(g, state, params)
        params = optax.apply_updates(params, updates)
        assert all(bool(jnp.all(jnp.isfinite(x))) for x in jax.tree_util.tree_leaves(params))
    stats = gradients.guard_stats(state)
    assert int(stats["grad/skipped"]) == 2 and int(stats["grad/updates"]) == 4
    # a skipped update changes nothing, not even Adam's moments
    updates, _ = gradients.nan_guard().update(bad, gradients.nan_guard().init(params))
    assert all(float(jnp.abs(u).max()) == 0 for u in jax.tree_util.tree_leaves(updates))


def test_clip_by_global_norm_scales_and_reports_raw_norm():
    t = gradients.clip_by_global_norm(1.0)
    g = {"a": jnp.array([3.0, 4.0])}
    u, s = t.update(g, t.init(g))
    np.testing.assert_allclose(u["a"], [0.6, 0.8], rtol=1e-6)
    assert float(s.last_norm) == 5.0 and int(s.clipped) == 1
    u, s = t.update({"a": jnp.array([0.3, 0.4])}, s)
    np.testing.assert_allclose(u["a"], [0.3, 0.4], rtol=1e-6)
    assert int(s.clipped) == 1


def test_truncation_window_cuts_gradient_to_earlier_steps():
    sim = Sim.load("cartpole")
    d0 = sim.init(jnp.array([0.0, 0.2]))

    def final_x(actions, truncate):
        return sim.rollout(d0, actions, truncate=truncate)[1].qpos[-1, 1]

    a = jnp.zeros((12, 1))
    # jitted: in eager mode every primitive around the scan is compiled and run on its own (50 s)
    grad = jax.jit(jax.grad(final_x), static_argnums=1)
    full = grad(a, None)
    cut = grad(a, 5)  # stops at t = 0, 5, 10: only actions 10, 11 reach the end
    assert float(jnp.abs(full[:10]).min()) > 0
    assert float(jnp.abs(cut[:10]).max()) == 0.0
    np.testing.assert_allclose(cut[10:], full[10:], rtol=1e-5)
