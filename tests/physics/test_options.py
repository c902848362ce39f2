"""Options MJX refuses: those that only report run with a warning, the others stay refused."""

import warnings

import mujoco
import numpy as np
import pytest

from twinrl.physics import MuJoCoWarning, Sim
from twinrl.physics.sim import MJCFError

_BALL = """<mujoco><option><flag {flag}="enable"/></option><worldbody>
  <geom type="plane" size="1 1 0.1"/>
  <body pos="0 0 0.2"><freejoint/><geom type="sphere" size="0.05"/></body>
</worldbody></mujoco>"""


def test_energy_reporting_is_simulated_off_with_one_warning():
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        sim = Sim.load(_BALL.format(flag="energy"))
    ours = [str(w.message) for w in said if issubclass(w.category, MuJoCoWarning)]
    assert len(ours) == 1 and "mjENBL_ENERGY" in ours[0] and "simulated without it" in ours[0]
    # the MuJoCo model keeps the flag (C still reports energy); the simulation runs
    assert sim.mj_model.opt.enableflags & mujoco.mjtEnableBit.mjENBL_ENERGY
    assert not sim.model.opt.enableflags & mujoco.mjtEnableBit.mjENBL_ENERGY
    d = sim.step(sim.init(), np.zeros(0))
    assert np.all(np.isfinite(np.asarray(d.qpos))) and float(d.qpos[2]) < 0.2


def test_an_option_that_changes_dynamics_stays_refused():
    with pytest.raises(MJCFError, match="mjENBL_OVERRIDE"):
        Sim.load(_BALL.format(flag="override"))


_CAPSULES = """<mujoco><custom>{own}</custom><worldbody><geom type="plane" size="2 2 0.1"/>
  {bodies}</worldbody></mujoco>"""


def _capsules(n: int, own: str = "") -> str:
    bodies = "".join(f'<body pos="{0.3 * i} 0 0.2"><freejoint/>'
                     f'<geom type="capsule" size="0.05 0.1"/></body>' for i in range(n))
    return _CAPSULES.format(own=own, bodies=bodies)


def test_contact_bounds_set_or_override_mjx_numerics_and_bound_the_candidates():
    # MJX evaluates every candidate pair each step (6 capsules: 15 capsule pairs of 1 contact,
    # 6 capsule-plane pairs of 2); max_geom_pairs keeps the nearest pairs of each function
    # (planes excepted), max_contact_points the deepest contacts of each dimension
    free = Sim.load(_capsules(6))
    assert free.init()._impl.contact.dist.shape[0] == 15 + 2 * 6
    pairs = Sim.load(_capsules(6), max_geom_pairs=3)
    assert pairs.init()._impl.contact.dist.shape[0] == 3 + 2 * 6
    points = Sim.load(_capsules(6), max_contact_points=10)
    assert points.init()._impl.contact.dist.shape[0] == 10
    # a bound the MJCF sets itself is kept, and replaced when given
    own = '<numeric name="max_geom_pairs" data="5"/>'
    assert Sim.load(_capsules(6, own)).init()._impl.contact.dist.shape[0] == 5 + 2 * 6
    assert Sim.load(_capsules(6, own), max_geom_pairs=2).init()._impl.contact.dist.shape[0] \
        == 2 + 2 * 6
    # the bounded model steps like the unbounded one when the kept pairs hold every contact
    # (capsules 0.3 apart: none touches another)
    a = np.asarray(free.step(free.init(), np.zeros(0)).qpos)
    b = np.asarray(pairs.step(pairs.init(), np.zeros(0)).qpos)
    np.testing.assert_allclose(a, b, atol=1e-7)
    with pytest.raises(ValueError, match="max_geom_pairs must be >= 1, got 0"):
        Sim.load(_capsules(2), max_geom_pairs=0)
