"""The fixed-iteration solve: same forward results as stock MJX, reverse mode that works."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco.mjx._src import math as mjx_math

from twinrl.physics import SCENES, Sim
from twinrl.physics.integrator import quat_integrate
from twinrl.physics.scenes import scenario


@pytest.fixture(scope="module")
def sims(x64):
    return {name: Sim.load(name) for name in SCENES}


@pytest.mark.parametrize("name", SCENES)
def test_forward_equals_stock_mjx_over_200_steps(sims, name):
    with jax.enable_x64(True):
        sim = sims[name]
        sc = scenario(name, sim.nq, sim.nv, sim.nu, sim.mj_model.qpos0, horizon=200)
        d0, actions = sim.init(sc.qpos, sc.qvel), jnp.asarray(sc.actions)
        ours = jax.jit(lambda d, a: sim.rollout(d, a)[1])(d0, actions)
        stock = jax.jit(lambda d, a: sim.rollout(d, a, step_fn=sim.stock_step)[1])(d0, actions)
        assert ours.qpos.dtype == jnp.float64
        assert float(jnp.max(jnp.abs(ours.qpos - stock.qpos))) <= 1e-6
        assert float(jnp.max(jnp.abs(ours.qvel - stock.qvel))) <= 1e-5
        if name != "cartpole":  # the scenario must exercise the solve
            assert int((ours.n_active > 0).sum()) > 0


def test_stock_mjx_cannot_reverse_differentiate_through_contacts(sims):
    # The reason twinrl.physics.solver exists (upstream mujoco issue #2259).
    with jax.enable_x64(True):
        sim = sims["push"]
        d0 = sim.init()

        def loss(a):
            return jnp.sum(sim.stock_step(d0, a).qpos)

        # traced under jit: the error comes from tracing the transpose, and eager mode would
        # compile and run every primitive of the step one by one first (~50 s)
        with pytest.raises(ValueError, match="while_loop"):
            jax.jit(jax.grad(loss))(jnp.zeros(sim.nu))
        # (ours differentiates the same step: see test_gradcheck.py)


def test_quat_integrate_matches_stock_and_has_the_right_derivative_at_rest(x64):
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        q = jnp.asarray(rng.normal(size=4))
        q = q / jnp.linalg.norm(q)
        # jitted: one compile each, not every operation compiled on its own
        ours = jax.jit(lambda w: quat_integrate(q, w, 0.01))
        stock = jax.jit(lambda w: mjx_math.quat_integrate(q, w, 0.01))
        for w in [rng.normal(size=3), np.zeros(3), 1e-5 * rng.normal(size=3)]:
            w = jnp.asarray(w)
            np.testing.assert_allclose(ours(w), stock(w), atol=1e-12)
        # At w = 0 the new orientation moves by dt/2 * (q ⊗ [0, e_i]) per unit of w_i.
        jac = jax.jit(jax.jacfwd(ours))(jnp.zeros(3))
        h = 1e-7
        fd = jnp.stack([(ours(h * e) - ours(-h * e)) / (2 * h) for e in jnp.eye(3)], axis=1)
        np.testing.assert_allclose(jac, fd, atol=1e-8)
        assert float(jnp.abs(jac).max()) > 1e-3  # stock MJX gives exactly 0 here
        assert float(jnp.abs(jax.jit(jax.jacfwd(stock))(jnp.zeros(3))).max()) == 0.0


@pytest.mark.parametrize("name", ["pendulum", "push", "peg_in_hole"])
def test_no_nonfinite_gradient_float32_vmapped_with_and_without_contacts(name):
    # float32 and vmap (lax.cond lowered to select) is where a solve's backward can produce NaN.
    sim = Sim.load(name)
    q = np.array(sim.mj_model.qpos0)
    if name == "push":
        q[2], q[4] = 0.3, 0.05  # box at rest on the floor, pusher far: contacts, no motion
    states = [(q, np.zeros(sim.nv)), (q, 0.3 * np.ones(sim.nv))]
    if name == "pendulum":
        states.append((np.array([-3.8]), np.array([-2.0])))  # into the limit
    if name == "peg_in_hole":
        states.append((np.array([0.0, 0.05]), np.zeros(2)))  # free space above the hole
    qp = jnp.asarray(np.stack([s[0] for s in states]), jnp.float32)
    qv = jnp.asarray(np.stack([s[1] for s in states]), jnp.float32)
    acts = jnp.zeros((len(states), 25, sim.nu)).at[1:].set(0.3)
    p0 = sim.default_params()

    def loss(a, qpos, qvel, params):
        _, tr = sim.rollout(sim.init(qpos, qvel), a, params)
        return jnp.sum(tr.qpos ** 2) + jnp.sum(tr.qvel ** 2)

    grads = jax.jit(jax.vmap(jax.grad(loss, argnums=(0, 1, 2, 3)),
                             in_axes=(0, 0, 0, None)))(acts, qp, qv, p0)
    leaves = jax.tree_util.tree_leaves(grads)
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in leaves)
    assert float(jnp.abs(grads[0]).max()) > 0  # actions matter


def test_a_solve_gone_nan_stops_at_once_and_a_finite_one_is_unchanged(sims):
    # Stock's convergence test compares NaN with the tolerance, never true: a NaN solve ran all
    # of its iterations (each with its whole line search) and, under vmap, held its batch for as
    # long. Ours stops it; a finite solve runs exactly as before.
    from mujoco.mjx._src import solver as stock

    from twinrl.physics import solver

    with jax.enable_x64(True):
        sim = sims["push"]
        sc = scenario("push", sim.nq, sim.nv, sim.nu, sim.mj_model.qpos0, horizon=30)
        # 20 steps in: the box rests on the floor. The last step's forward left a consistent
        # set (its constraint rows, qacc_smooth): the solve to run again, from qacc_smooth.
        d = sim.rollout(sim.init(sc.qpos, sc.qvel), jnp.asarray(sc.actions)[:20])[0]
        d = d.replace(qacc=d.qacc_smooth)
        m = sim.model
        n_iter = int(m.opt.iterations)

        def run(d):
            ctx = solver.converge(m, d, stock.Context.create(m, d), n_iter)
            return ctx.solver_niter, ctx.qacc

        niter, qacc = jax.jit(run)(d)
        assert 0 < int(niter) < n_iter and bool(jnp.all(jnp.isfinite(qacc)))
        assert bool(jnp.any(qacc != d.qacc_smooth))  # the constraints acted
        bad = d.replace(qacc_smooth=d.qacc_smooth.at[0].set(jnp.nan))
        bad = bad.replace(qacc=bad.qacc_smooth)
        niter_bad, _ = jax.jit(run)(bad)
        assert int(niter_bad) <= 1, int(niter_bad)
