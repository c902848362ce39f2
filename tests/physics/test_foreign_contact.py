"""Gradients through sliding friction and an actuated pusher (float64, T = 30, against central
differences); and why the solve's derivative is implicit. (The arm scenes, the slowest, have files
of their own so the suite's two workers share them.)"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.physics._foreign import FOREIGN, check_foreign_scene
from twinrl.physics import Sim
from twinrl.physics.gradcheck import gradcheck


@pytest.mark.parametrize("name", ["box_sliding", "box_pushed"])
def test_contact_scene_passes_gradcheck_with_every_group_judged(x64, name):
    check_foreign_scene(name)


FLAT_BOX = """<mujoco><option timestep="0.005"/><worldbody><geom type="plane" size="1 1 0.1"/>
<body pos="0 0 0.07"><freejoint/><geom type="box" size="0.05 0.05 0.05" mass="0.3"/></body>
</worldbody></mujoco>"""


def test_implicit_solve_derivative_is_right_where_the_unrolled_one_is_not(x64):
    # A box landing flat on 4 corners (the case reported from a user's MJCF): at the step of
    # deepest impact, the unrolled solve's Jacobian was 2,991 against 25.7 by differences.
    with jax.enable_x64(True):
        errors = {}
        for mode in ("implicit", "unrolled"):
            sim = Sim.load(FLAT_BOX, gradient=mode)
            step = jax.jit(lambda d: sim.step(d, jnp.zeros(0)))
            d = sim.init()
            for _ in range(15):
                d = step(d)
            assert int(jnp.sum(d._impl.efc_force != 0)) > 0  # in contact

            def f(x, d=d, step=step):
                d1 = step(d.replace(qvel=x))
                return jnp.concatenate([d1.qpos, d1.qvel])

            jac = np.asarray(jax.jacrev(f)(d.qvel))
            h = 1e-7
            fd = np.stack([(np.asarray(f(d.qvel.at[i].add(h))) - np.asarray(f(d.qvel.at[i].add(-h))))
                           / (2 * h) for i in range(sim.nv)], axis=1)
            errors[mode] = np.abs(jac - fd).max() / np.abs(fd).max()
    assert errors["implicit"] < 1e-6, errors
    assert errors["unrolled"] > 1.0, errors  # the reason for the implicit derivative


def test_the_flat_box_passes_gradcheck_on_measured_noise_and_the_unrolled_solve_still_fails(x64):
    """The flat box's tilt derivatives are rounding noise in exact-arithmetic zeros: gradcheck
    measures that noise (inputs moved by 1e-13) instead of failing on it, and the noise it allows
    is too small to hide the unrolled solve's error on the same box."""
    with jax.enable_x64(True):
        r = gradcheck(Sim.load(FLAT_BOX), horizon=20, scenario="zero")
        assert r.failures == [] and r.nan_count == 0 and r.count("resolved") >= 3
        tilt = [x for x in r.rows if x["group"] == "params.armature" and x["index"] in "34"]
        assert all(x["status"] != "resolved" for x in tilt)
        assert max(x["grad_noise"] for x in tilt) > max(abs(x["grad"]) for x in tilt) / 10
        # the forward's own roughness, reported: an ulp-sized move of the resting box moves its
        # loss by ~1e-9 beyond the gradient's prediction (a pendulum's: ~1e-15)
        assert 1e-11 < r.loss_jitter < 1e-6 and r.summary()["loss_jitter"] == r.loss_jitter
        unrolled = gradcheck(Sim.load(FLAT_BOX, gradient="unrolled"), horizon=20,
                             scenario="zero")
    bad = [x for x in unrolled.failures if x["status"] == "resolved"]
    assert bad and max(abs(x["grad"]) / abs(x["fd"]) for x in bad) > 1e3, unrolled.failures


def test_foreign_scenes_are_not_bundled_scenes():
    sim = Sim.load(FOREIGN / "box_drop.xml")
    assert not sim.bundled and sim.name == "box_drop"


def test_tied_friction_is_judged_by_scaling_the_group(x64):
    # MuJoCo gives a contact the larger of its geoms' frictions. With floor and box tied (one
    # default friction for every geom, as most users' MJCFs have it), each coefficient alone sits
    # at that max's kink: no single friction entry can be resolved (backward difference 0). The
    # group's 'scale' entry is smooth through the tie and must be resolved and right.
    xml = (FOREIGN / "box_sliding.xml").read_text().replace('friction="1 0.005', 'friction="0.8 0.005')
    assert xml.count('friction="0.8 0.005 0.0001"') == 2
    with jax.enable_x64(True):
        r = gradcheck(Sim.load(xml), horizon=30, scenario="zero")
    rows = [x for x in r.rows if x["group"] == "params.friction"]
    acting = [x for x in rows if x["index"] != "scale" and x["grad"] != 0]
    assert len(acting) == 2 and all(x["status"] != "resolved" for x in acting)
    scale = next(x for x in rows if x["index"] == "scale")
    assert scale["status"] == "resolved" and scale["rel_err"] <= 1e-4, scale
    # the scale entry's gradient is the group's gradient along the group: g . x
    assert scale["grad"] == pytest.approx(0.8 * sum(x["grad"] for x in acting), rel=1e-12)
    assert r.passed_strict and r.nan_count == 0
