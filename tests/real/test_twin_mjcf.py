"""A real twin of a user's own MJCF (``RealTwin(envs.from_mjcf(...))``): MuJoCo C with a hidden
perturbation, the task's reward and observation, a camera where the MJCF has none; Real2Sim
through ``sysid.collect`` recovers what was perturbed. ``tests/_turntable.py``'s one-joint arm,
as ``tests/envs/test_mjcf_reward.py`` learns in it, so nothing new compiles but the fit."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from twinrl import envs
from twinrl.real import RealTwin, make_real
from twinrl.real.perturbation import Perturbation
from twinrl.real2sim import sysid
from tests._turntable import ARM


def turn(qpos, qvel, action):
    return -(qpos[0] - 1.0) ** 2


@pytest.fixture(scope="module")
def arm():
    return envs.from_mjcf(ARM, name="turntable", reward=turn, episode_length=40, frame_skip=5)


def test_an_unperturbed_twin_follows_the_simulator(arm):
    twin = RealTwin(arm, perturbation=Perturbation.none(), integrator="euler")
    obs, _ = twin.reset(seed=0)
    state = arm.reset(None)
    for t in range(20):
        a = np.array([np.sin(0.3 * t)], np.float32)
        obs, r, term, trunc, info = twin.step(a)
        state = arm.step(state, jnp.asarray(a))
        np.testing.assert_allclose(obs, np.asarray(state.obs), atol=2e-4)
        assert r == pytest.approx(float(state.reward), abs=1e-3) and not term
    assert twin.task_name == "turntable" and twin.camera == -1  # no camera: MuJoCo's free one
    rgb = twin.render_images(kinds=("rgb",))["rgb"]
    assert rgb.shape == (240, 320, 3) and rgb.std() > 1.0
    with pytest.raises(ValueError, match="free camera, has no pose in the MJCF"):
        twin.nominal_camera()
    twin.close()


def test_bad_task_arguments_are_one_line_errors(arm):
    with pytest.raises(ValueError, match="config overrides are for a task name"):
        make_real(arm, config={"episode_length": 10})
    with pytest.raises(TypeError, match="task must be a task name or a twinrl.envs.Env"):
        RealTwin(3)


def test_the_default_perturbation_is_hidden_and_seeded(arm):
    a, b, c = (RealTwin(arm, seed=s) for s in (0, 0, 1))
    masses = [t.oracle().params.mass for t in (a, b, c)]
    np.testing.assert_array_equal(masses[0], masses[1])
    assert not np.allclose(masses[0], masses[2])
    assert not np.allclose(masses[0], arm.sim.mj_model.body_mass[1:])
    for t in (a, b, c):
        t.close()


def test_sysid_recovers_the_twins_damping_and_gain(arm):
    """The arm's inertia known (its mass), the twin's damping 1.5x and gain 0.9x come back."""
    pert = dataclasses.replace(Perturbation.none(), damping_scale=(1.5,), gain_scale=(0.9,))
    twin = make_real(arm, perturbation=pert)
    data = sysid.collect(twin, episodes=2, policy="open_loop")
    twin.close()
    fit = sysid.fit(arm, data, sysid.SysidConfig(params=("damping/hinge", "gain/motor"),
                                                  known=(("mass/link", 0.5),), max_latency=0))
    got = dict(zip(fit.names, fit.values))
    assert got["damping/hinge"] == pytest.approx(0.3, rel=0.02)
    assert got["gain/motor"] == pytest.approx(0.9, rel=0.02)
