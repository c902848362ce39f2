"""A model with a tendon in float64: MJX 3.17's step returns its tendon-wrap ints as int64 where
``make_data`` made them int32, which broke every ``lax.scan`` rollout (and so gradcheck) of such
a model; our step returns the dtypes it was given."""

import jax
import jax.numpy as jnp
import numpy as np

from tests.physics._foreign import FOREIGN
from twinrl.physics import Sim
from twinrl.physics.gradcheck import gradcheck


def test_a_tendon_arm_rolls_out_in_float64_like_stock_mjx_and_passes_gradcheck(x64):
    with jax.enable_x64(True):
        sim = Sim.load(FOREIGN / "tendon_arm.xml")
        actions = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (20, sim.nu)))
        ours = jax.jit(lambda a: sim.rollout(sim.init(), a)[1])(actions)
        stock = jax.jit(lambda a: sim.rollout(sim.init(), a, step_fn=sim.stock_step)[1])(actions)
        assert ours.qpos.dtype == jnp.float64
        np.testing.assert_allclose(ours.qpos, stock.qpos, atol=1e-9)
        r = gradcheck(sim, horizon=30, scenario="wave")
    assert r.passed_strict and r.nan_count == 0 and r.max_rel_error <= 1e-4
    assert r.count("resolved") >= 0.6 * len(r.rows)
