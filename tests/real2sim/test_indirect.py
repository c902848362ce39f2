"""Indirect inference removes an estimator's noise bias; the noise sd is read off quaternions."""

import mujoco
import numpy as np
import pytest

from twinrl.real2sim.sysid.indirect import indirect, noise_sd_from_quaternions

NOISE = 0.7  # sd of the noise on the regressor: OLS shrinks a slope by 1 / (1 + 0.49)
TRUE = np.array([2.0, 0.5])


def simulate(theta, seed, n=2000):
    """Errors in variables: y1 = a x, y2 = c x (+ small noise), x observed with NOISE."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=n)
    return {"x": x + rng.normal(0.0, NOISE, n),
            "y1": theta[0] * x + rng.normal(0.0, 0.1, n),
            "y2": theta[1] * x + rng.normal(0.0, 0.1, n)}


def estimate(d):
    """Two OLS slopes, reported coupled (s1, s1 * s2), so the binding function's Jacobian is not
    diagonal: the first fixed-point step alone cannot solve it."""
    s1 = float(d["x"] @ d["y1"] / (d["x"] @ d["x"]))
    s2 = float(d["x"] @ d["y2"] / (d["x"] @ d["x"]))
    return np.array([s1, s1 * s2])


def naive(values):
    """What the estimator's values say the parameters are, read as if it were unbiased."""
    return np.array([values[0], values[1] / values[0]])


def test_indirect_removes_the_attenuation_bias():
    real = simulate(TRUE, seed=1)
    raw = naive(estimate(real))
    assert np.all(np.abs(raw / TRUE - 1) > 0.25)  # the estimator is biased by a third
    res = indirect(estimate, simulate, real, reps=4, iterations=6, seed=100)
    np.testing.assert_allclose(res.values, TRUE, rtol=0.04)
    np.testing.assert_allclose(res.raw, estimate(real))
    # the Jacobian of log E w.r.t. log theta is [[1, 0], [1, 1]] here (E is multiplicative)
    np.testing.assert_allclose(res.jacobian, [[1.0, 0.0], [1.0, 1.0]], atol=0.15)
    assert len(res.history) == 6 and res.iterates.shape == (6, 2)


def test_indirect_sd_matches_the_spread_over_real_datasets():
    fits, sds = [], []
    for s in range(8):
        res = indirect(estimate, simulate, simulate(TRUE, seed=s), reps=4, iterations=4,
                       seed=1000)
        fits.append(np.log(res.values))
        sds.append(res.sd / res.values)
    spread = np.std(fits, axis=0, ddof=1)
    ratio = np.mean(sds, axis=0) / spread
    assert np.all((ratio > 0.4) & (ratio < 2.5)), (ratio, spread)


def test_indirect_refuses_bad_input():
    with pytest.raises(ValueError, match="reps >= 2"):
        indirect(estimate, simulate, simulate(TRUE, 0), reps=1)
    with pytest.raises(ValueError, match="not all positive"):
        indirect(lambda d: np.array([-1.0, 1.0]), simulate, simulate(TRUE, 0))


def test_noise_sd_from_quaternions():
    m = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><freejoint/><geom size='0.1'/></body>"
        "<body pos='1 0 0'><joint type='ball'/><geom size='0.1'/></body></worldbody></mujoco>")
    rng = np.random.default_rng(0)
    q = np.tile(m.qpos0, (4000, 1))
    rot = rng.normal(size=(4000, 4))
    q[:, 3:7] = rot / np.linalg.norm(rot, axis=1, keepdims=True)  # any unit quaternions
    noisy = q + rng.normal(0.0, 0.002, q.shape)
    assert noise_sd_from_quaternions(m, noisy) == pytest.approx(0.002, rel=0.05)
    assert noise_sd_from_quaternions(m, q) < 1e-12
    with pytest.raises(ValueError, match="nq = 11"):
        noise_sd_from_quaternions(m, q[:, :7])
    hinge = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><joint/><geom size='0.1'/></body></worldbody></mujoco>")
    with pytest.raises(ValueError, match="no free or ball joint"):
        noise_sd_from_quaternions(hinge, np.zeros((3, 1)))
