"""``bench/sysid_baseline.py``: twinrl's parameter names map onto the same ``MjModel`` entries for
``mujoco.sysid`` as ``PhysParams`` writes (a mass scales its body's inertia alike)."""

import importlib.util
from pathlib import Path

import mujoco
import numpy as np
import pytest

from twinrl import envs
from twinrl.real2sim.sysid.config import parse_param

BENCH = Path(__file__).resolve().parents[2] / "bench"

XML = """<mujoco><worldbody>
  <body name="a"><joint name="ja" type="slide" damping="0.3"/>
    <geom size=".1" mass="2"/>
    <body name="b" pos="0 0 .5"><joint name="jb" type="hinge" frictionloss=".01"/>
      <geom size=".05" mass="0.5"/></body></body></worldbody>
  <actuator><motor name="m" joint="ja" gear="3" ctrlrange="-1 1"/></actuator></mujoco>"""


@pytest.fixture(scope="module")
def bench():
    import sys

    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location("sysid_baseline", BENCH / "sysid_baseline.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_parameters_map_to_the_physparams_fields(bench):
    env = envs.from_mjcf(XML)
    nominal = mujoco.MjModel.from_xml_string(XML)
    m = mujoco.MjModel.from_xml_string(XML)
    names = ["mass/b", "damping/ja", "frictionloss/jb", "gain/m"]
    bench.write_params(m, nominal, [parse_param(env, n) for n in names], [1.0, 0.6, 0.02, 1.5])
    b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "b")
    assert m.body_mass[b] == 1.0
    np.testing.assert_allclose(m.body_inertia[b], 2 * nominal.body_inertia[b])
    assert m.dof_damping[0] == 0.6 and m.dof_frictionloss[1] == 0.02
    assert m.actuator_gainprm[0, 0] == 1.5
    a = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "a")  # untouched
    assert m.body_mass[a] == nominal.body_mass[a]
    with pytest.raises(ValueError, match="gravity"):
        bench.model_field(m, "gravity", 0)
