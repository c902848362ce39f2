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


def test_merge_replaces_a_rerun_dataset_and_keeps_the_others_provenance(bench, tmp_path):
    import argparse
    import json

    path = tmp_path / "sysid_baseline.json"
    old_meta = {"command": "python bench/sysid_baseline.py", "commit": "a" * 40, "dirty": False,
                "date": "2026-01-01T00:00:00Z", "machine": {"load_average": [1.0, 1.0, 1.0]}}
    path.write_text(json.dumps({"meta": old_meta, "results": [
        {"dataset": "pendulum_swingup", "v": 1}, {"dataset": "cartpole_swingup", "v": 1}]}))
    base = bench.committed_rows(path)
    args = argparse.Namespace(datasets=["cartpole_swingup", "panda"])
    bench.write_rows(path, base, [{"dataset": "cartpole_swingup", "v": 2},
                                  {"dataset": "panda (user MJCF)", "v": 2}], args)
    doc = json.loads(path.read_text())
    assert [(r["dataset"], r["v"]) for r in doc["results"]] == [
        ("pendulum_swingup", 1), ("cartpole_swingup", 2), ("panda (user MJCF)", 2)]
    rows = doc["meta"]["rows"]
    assert rows["pendulum_swingup"]["commit"] == "a" * 40
    assert rows["pendulum_swingup"]["load_average"] == [1.0, 1.0, 1.0]
    assert rows["cartpole_swingup"]["commit"] != "a" * 40
    assert rows["panda (user MJCF)"] == rows["cartpole_swingup"]
    # without --merge (an empty base) only this run's rows are written
    bench.write_rows(path, {"results": [], "rows": {}}, [{"dataset": "panda (user MJCF)"}], args)
    assert [r["dataset"] for r in json.loads(path.read_text())["results"]] == [
        "panda (user MJCF)"]
