"""``twinrl.real2sim.lm.minimise``, the Levenberg-Marquardt loop both Real2Sim fits share, on
small problems with known answers (plain NumPy: no compile)."""

import numpy as np
import pytest

from twinrl.real2sim.lm import Linearisation, minimise


def rosenbrock(p):
    """Rosenbrock's function as residuals: ``|r|^2 = 100 (y - x^2)^2 + (1 - x)^2``, minimum 0 at
    (1, 1), a curved valley on which Gauss-Newton alone overshoots."""
    x, y = p
    return np.array([10.0 * (y - x * x), 1.0 - x]), np.array([[-20.0 * x, 10.0], [-1.0, 0.0]])


def dense(res_jac, flip=lambda lam: False):
    """``linearise`` of ``0.5 |r|^2`` with Marquardt's diagonal scaling; ``flip(lam)`` makes a
    solve return the step reversed (uphill), to test rejection."""
    calls = []

    def linearise(p):
        r, J = res_jac(p)
        A, g = J.T @ J, J.T @ r

        def solve(lam):
            step = -np.linalg.solve(A + lam * np.diag(np.diag(A)), g)
            return -step if flip(lam) else step

        def evaluate(step):
            rc = res_jac(p + step)[0]
            calls.append((p, step))
            return p + step, 0.5 * rc @ rc

        return Linearisation(0.5 * r @ r, solve, evaluate)

    return linearise, calls


def test_converges_on_rosenbrock():
    linearise, _ = dense(rosenbrock)
    res = minimise(linearise, np.array([-1.2, 1.0]), damping=1e-3, iterations=200,
                   rtol_initial=1e-20)
    np.testing.assert_allclose(res.x, [1.0, 1.0], atol=1e-6)
    assert res.cost < 1e-12 and res.cost0 == pytest.approx(12.1)
    costs = [rec["cost"] for rec in res.log]
    assert all(b <= a for a, b in zip(costs, costs[1:]))   # the kept cost never rises
    assert res.iterations == len(res.log) and res.stop in ("no decrease", "small decrease")


def test_a_step_that_raises_the_cost_is_rejected():
    # below lam = 1 every solve points uphill: those candidates are evaluated and thrown away,
    # lam grows by 4 per rejection until the (honest) step is taken
    linearise, calls = dense(rosenbrock, flip=lambda lam: lam < 1.0)
    p0 = np.array([-1.2, 1.0])
    res = minimise(linearise, p0, damping=1e-2, iterations=1)
    first = res.log[0]
    assert first["accepted"] and first["tries"] == 5      # 1e-2 * 4^k < 1 for k = 0..3
    assert len(calls) == 5 and all(np.array_equal(p, p0) for p, _ in calls)
    cost = lambda p: 0.5 * np.sum(rosenbrock(p)[0] ** 2)  # noqa: E731
    assert all(cost(p0 + s) >= cost(p0) for _, s in calls[:4])
    np.testing.assert_array_equal(res.x, p0 + calls[4][1])
    assert res.cost < res.cost0
    assert first["damping"] == pytest.approx(1e-2 * 4 ** 4 / 3)


def test_no_decrease_stops_and_keeps_the_start():
    linearise, calls = dense(rosenbrock, flip=lambda lam: True)
    p0 = np.array([-1.2, 1.0])
    res = minimise(linearise, p0, damping=1e-3, iterations=50, tries=6)
    assert res.stop == "no decrease" and res.iterations == 1 and len(calls) == 6
    np.testing.assert_array_equal(res.x, p0)
    assert res.cost == res.cost0 and not res.log[0]["accepted"]


def test_singular_systems_raise_the_damping():
    seen = []

    def linearise(p):
        def solve(lam):
            seen.append(lam)
            if lam < 1.0:
                raise np.linalg.LinAlgError("singular")
            return -p / (1.0 + lam)
        return Linearisation(0.5 * p @ p, solve, lambda s: (p + s, 0.5 * (p + s) @ (p + s)))

    res = minimise(linearise, np.array([2.0]), damping=0.01, iterations=1)
    assert seen == pytest.approx([0.01, 0.1, 1.0]) and res.log[0]["tries"] == 3
    assert res.cost < res.cost0


def test_stopping_rules_and_callback():
    linearise, _ = dense(rosenbrock)
    seen = []
    res = minimise(linearise, np.array([-1.2, 1.0]), damping=1e-3, iterations=200, rtol=0.5,
                   callback=lambda x, rec: seen.append((x.copy(), rec)))
    assert res.stop == "small decrease" and res.iterations < 200
    assert [rec for _, rec in seen] == list(res.log)
    np.testing.assert_array_equal(seen[-1][0], res.x)
    res = minimise(linearise, np.array([-1.2, 1.0]), damping=1e-3, iterations=200,
                   step_tol=10.0, step_size=lambda s: float(np.max(np.abs(s))))
    assert res.stop == "small step" and res.iterations == 1
    res = minimise(linearise, np.array([-1.2, 1.0]), damping=1e-3, iterations=3)
    assert res.stop == "iterations" and res.iterations == 3
    with pytest.raises(ValueError, match="damping > 0"):
        minimise(linearise, np.zeros(2), damping=0.0, iterations=3)
