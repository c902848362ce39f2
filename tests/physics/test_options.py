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
