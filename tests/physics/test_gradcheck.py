"""gradcheck: reverse mode vs float64 central differences on every bundled scene."""

import jax
import numpy as np
import pytest

from twinrl.physics import SCENES, Sim
from twinrl.physics.gradcheck import classify, combine_summaries, gradcheck
from twinrl.physics.integrator import tangent_delta, tangent_qpos

# Shorter than `twinrl gradcheck`'s defaults (100; 50 for peg_in_hole) to keep the suite fast, but
# long enough that each constrained scene has both free and constrained steps (asserted below).
HORIZON = {"cartpole": 40, "pendulum": 40, "push": 30, "peg_in_hole": 40}


@pytest.mark.parametrize("name", SCENES)
def test_gradcheck_passes_in_float64(x64, name):
    with jax.enable_x64(True):
        r = gradcheck(Sim.load(name), horizon=HORIZON[name])
    assert r.dtype == "float64"
    assert r.nan_count == 0
    assert r.failures == [], r.failures[:5]
    assert r.max_rel_error <= 1e-4
    # most entries must be judged, not waved through as kinks
    assert r.count("resolved") >= 0.5 * len(r.rows)
    assert r.count("kink") <= 0.1 * len(r.rows)
    if name != "cartpole":
        assert r.constrained_steps > 0 and r.free_steps > 0
    if name == "pendulum":  # smooth: an ulp-sized move of every input changes the loss as its
        assert r.loss_jitter < 1e-13  # gradient says, to rounding (measured 1.2e-15)
    groups = {g["group"] for g in r.groups}
    assert {"actions", "qpos", "qvel", "params.mass", "params.damping", "params.friction",
            "params.gain", "params.gravity"} <= groups


def test_classify_catches_wrong_gradients_and_kinks():
    fd = np.array([1.0, 1.0, 1e-9, 1.0, 1.0])
    fd4 = fd.copy()
    fwd, bwd = fd.copy(), fd.copy()
    fwd[4], bwd[4] = 1.5, 0.5          # symmetric kink: central differences agree, sides don't
    g = np.array([1.0 + 1e-6, 1.01, 1e-9 + 1e-12, 1.0 + np.nan, 3.0])
    rounding = np.full(5, 1e-10)
    status, ok, rel, _ = classify(g, fd, fd4, fwd, bwd, rounding, rtol=1e-4)
    assert list(status) == ["resolved", "resolved", "noise", "resolved", "kink"]
    assert list(ok) == [True, False, True, False, True]


def test_classify_leaves_differences_outside_the_models_range_unjudged():
    # a non-finite difference (the step left the model's valid range) is "outside": not judged;
    # a non-finite gradient still fails
    fd = np.array([np.nan, 1.0, np.nan])
    status, ok, _, _ = classify(np.array([2.0, 1.0, np.nan]), fd, fd, fd, fd,
                                np.full(3, 1e-10), rtol=1e-4)
    assert list(status) == ["outside", "resolved", "outside"]
    assert list(ok) == [True, True, False]


def test_a_step_below_a_tiny_inertia_is_shrunk_not_failed(x64, tmp_path):
    # A fin of 1e-7 inertia without armature (the Control Suite's fish): an armature step of
    # 4e-6 below zero leaves the mass matrix indefinite and the loss NaN. Such entries are
    # differenced again with a smaller step instead of failing the check.
    path = tmp_path / "fin.xml"
    path.write_text(
        '<mujoco><option timestep="0.004" gravity="0 0 0"/><worldbody><body>'
        '<joint name="big" type="hinge" axis="0 0 1" damping="0.01"/>'
        '<geom type="box" size="0.1 0.05 0.02" mass="0.5"/>'
        '<body pos="0.1 0 0"><joint name="fin" type="hinge" axis="1 0 0" damping="2e-5"/>'
        '<inertial pos="0 0 0" mass="1e-4" diaginertia="1e-7 1e-7 1e-7"/></body>'
        '</body></worldbody><actuator><motor joint="big" gear="0.01"/>'
        '<motor joint="fin" gear="1e-5"/></actuator></mujoco>')
    with jax.enable_x64(True):
        sim = Sim.load(path)
        r = gradcheck(sim, horizon=10)
    assert r.nan_count == 0 and r.failures == [], r.failures[:3]
    fin = next(x for x in r.rows if x["group"] == "params.armature" and x["index"] == "1")
    # judged at a smaller step: resolved, with its large gradient (the fin's inertia is tiny)
    assert fin["status"] == "resolved" and abs(fin["grad"]) > 1e3 and fin["rel_err"] < 1e-6


def test_tangent_delta_inverts_tangent_qpos_with_a_finite_jacobian_at_zero(x64):
    """sysid estimates window starts in these coordinates and weighs their offset from the
    recorded state: the offset must be the step that was taken, and differentiable at 0."""
    from mujoco.mjx._src.types import JointType

    jt = tuple(int(t) for t in (JointType.HINGE, JointType.FREE, JointType.BALL,
                                JointType.SLIDE))
    rng = np.random.default_rng(0)
    with jax.enable_x64(True):
        for scale in (1e-9, 0.5, 1.2):
            q0 = np.concatenate([[0.3], rng.normal(size=3), rng.normal(size=4),
                                 rng.normal(size=4), [0.1]])
            q0[4:8] /= np.linalg.norm(q0[4:8])
            q0[8:12] /= np.linalg.norm(q0[8:12])
            dq = scale * rng.normal(size=11)
            q1 = tangent_qpos(jt, q0, dq)
            np.testing.assert_allclose(np.linalg.norm(q1[4:8]), 1.0, rtol=1e-12)
            np.testing.assert_allclose(tangent_delta(jt, q0, q1), dq, atol=1e-12)
            # -q is the same rotation: the offset does not jump by a turn
            q1n = q1.at[8:12].multiply(-1.0)
            np.testing.assert_allclose(tangent_delta(jt, q0, q1n), dq, atol=1e-12)
        J = jax.jacfwd(lambda d: tangent_delta(jt, q0, tangent_qpos(jt, q0, d)))(np.zeros(11))
        np.testing.assert_allclose(J, np.eye(11), atol=1e-9)


def test_user_mjcf_gets_tangent_space_orientations_and_coverage_per_group(x64, tmp_path):
    # A user's file named like a bundled scene gets the generic scenario (it used to get push's,
    # an IndexError on another model), orientations are 3 rotation coordinates, and a group with
    # nothing resolved is reported (here: a free-flying box, 5 steps from rest: damping's effect
    # is below rounding; friction never acts, exactly).
    path = tmp_path / "push.xml"
    path.write_text('<mujoco><worldbody><body pos="0 0 1" euler="10 20 30"><freejoint name="b"/>'
                    '<geom type="box" size="0.1 0.2 0.3" mass="1"/></body></worldbody></mujoco>')
    with jax.enable_x64(True):
        sim = Sim.load(path)
        assert not sim.bundled
        r = gradcheck(sim, horizon=5)
    assert r.scenario == "wave" and r.passed
    qpos = [row for row in r.rows if row["group"] == "qpos"]
    assert [row["index"] for row in qpos] == ["0:b.x", "1:b.y", "2:b.z", "3:b.rx", "4:b.ry",
                                               "5:b.rz"]
    assert all(row["status"] == "resolved" for row in qpos[3:])  # rotations are judged
    groups = {g["group"]: g for g in r.groups}
    assert groups["params.frictionloss"]["inert"]  # no friction-loss rows: exactly no effect
    assert groups["params.friction"]["inert"]  # no contact
    assert r.unjudged == ["params.damping"] and not r.passed_strict
    with pytest.raises(ValueError, match="scenario 'push' is the bundled push scene's"):
        gradcheck(sim, horizon=5, scenario="push")
    with pytest.raises(ValueError, match="rtol must be > 0"):
        gradcheck(sim, horizon=5, rtol=0)


def test_gravity_cancelled_by_gravcomp_is_numerically_inert_and_entries_subset(x64, tmp_path):
    # A gravity-compensated 2-link arm driven by motors: gravity reaches the loss only through
    # rounding (~1e-18), so it is inert, not unjudged; damping acts and is judged. `entries`
    # differences a seeded subset per group and says so.
    path = tmp_path / "arm.xml"
    path.write_text(
        '<mujoco><option timestep="0.01"/><worldbody>'
        '<body gravcomp="1"><joint name="a" type="hinge" axis="0 1 0" damping="0.5"/>'
        '<geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>'
        '<body pos="0.3 0 0" gravcomp="1"><joint name="b" type="hinge" axis="0 1 0" '
        'damping="0.5"/><geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>'
        '</body></body></worldbody><actuator><motor joint="a"/><motor joint="b"/></actuator>'
        '</mujoco>')
    with jax.enable_x64(True):
        sim = Sim.load(path)
        r = gradcheck(sim, horizon=20, entries=3)
    groups = {g["group"]: g for g in r.groups}
    assert r.passed and r.max_rel_error <= 1e-4
    grav = groups["params.gravity"]
    assert grav["inert"] and grav["resolved"] == 0 and grav["max_abs_grad"] < 1e-12
    assert groups["params.damping"]["resolved"] >= 1
    assert groups["actions"]["entries"] == 3 and groups["actions"]["entries_total"] == 40
    assert groups["params.gravity"]["entries"] == 4  # its 3, all of them, and its scaling
    assert "params.gravity" not in r.unjudged


def test_several_scenes_summary_takes_the_worst_and_tags_every_row():
    a = {"scene": "a", "max_rel_error": 1e-6, "nan_count": 0, "passed": True, "rows": [{"i": 0}]}
    b = {"scene": "b", "max_rel_error": 3e-5, "nan_count": 2, "passed": False,
         "rows": [{"i": 0}, {"i": 1}]}
    s = combine_summaries([a, b])
    assert s["max_rel_error"] == 3e-5 and s["nan_count"] == 2 and s["passed"] is False
    assert [sc["scene"] for sc in s["scenes"]] == ["a", "b"]
    assert all("rows" not in sc for sc in s["scenes"])
    assert s["rows"] == [{"i": 0, "scene": "a"}, {"i": 0, "scene": "b"}, {"i": 1, "scene": "b"}]
    assert combine_summaries([a])["passed"] is True


def test_difference_batches_shrink_with_the_constraint_jacobian():
    # one batch of differenced rollouts holds ~EFC_COPIES constraint Jacobians per rollout: a
    # model with thousands of contact rows gets fewer rollouts per batch, a small one BATCH
    from twinrl.physics.gradcheck import BATCH, batch_size

    def capsules(n):
        bodies = "".join(f'<body pos="{0.3 * i} 0 0.2"><freejoint/>'
                         f'<geom type="capsule" size="0.05 0.1"/></body>' for i in range(n))
        return (f'<mujoco><worldbody><geom type="plane" size="9 9 0.1"/>{bodies}'
                f'</worldbody></mujoco>')

    assert batch_size(Sim.load(capsules(2))) == BATCH
    many = Sim.load(capsules(60))  # 1,770 capsule pairs: a 7,560 x 360 Jacobian (float32)
    assert 1 <= batch_size(many) < BATCH
