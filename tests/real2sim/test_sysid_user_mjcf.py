"""Real2Sim on a user's own MJCF (``envs.from_mjcf``): an arm written for this test, logged by
MuJoCo C with heavier and lighter links and other joint damping than its MJCF says (and a
massless frame for its tool site, as MJCFs have), identified
from (qpos, qvel, ctrl) logs through the Python API and ``twinrl sysid --env ARM.xml --from
LOG.npz``."""

import json

import mujoco
import numpy as np
import pytest

from twinrl import cli, envs
from twinrl.real2sim import sysid

ARM = """<mujoco model="my_arm">
  <option timestep="0.01" integrator="Euler"/>
  <worldbody>
    <body name="upper" pos="0 0 1">
      <joint name="shoulder" type="hinge" axis="0 1 0" damping="0.2"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1.0"/>
      <body name="fore" pos="0.3 0 0">
        <joint name="elbow" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.025" mass="0.6"/>
        <body name="tool_frame" pos="0.25 0 0"><site name="tool"/></body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="m_shoulder" joint="shoulder" ctrlrange="-8 8"/>
    <motor name="m_elbow" joint="elbow" ctrlrange="-4 4"/>
  </actuator>
</mujoco>"""
FITTED = ("mass/upper", "mass/fore", "damping/shoulder", "damping/elbow")
TRUTH = {"mass/upper": 1.15, "mass/fore": 0.54, "damping/shoulder": 0.3, "damping/elbow": 0.07}


def robot_logs(episodes=4, steps=150, seed=0):
    """The 'robot': MuJoCo C on the MJCF with TRUTH's masses (inertia scaled alike, as
    PhysParams scales it) and damping; held random torques. Returns qpos, qvel, ctrl."""
    m = mujoco.MjModel.from_xml_string(ARM)
    for body, scale in ((1, 1.15), (2, 0.9)):
        m.body_mass[body] *= scale
        m.body_inertia[body] *= scale
    m.dof_damping[:] = [0.3, 0.07]
    d = mujoco.MjData(m)
    mujoco.mj_setConst(m, d)
    rng = np.random.default_rng(seed)
    qp, qv, cs = [], [], []
    for _ in range(episodes):
        mujoco.mj_resetData(m, d)
        d.qpos[:] = rng.uniform(-0.5, 0.5, 2)
        ctrl = np.repeat(rng.uniform(-1, 1, (steps // 10, 2)) * [8, 4], 10, axis=0)
        q, v = [d.qpos.copy()], [d.qvel.copy()]
        for c in ctrl:
            d.ctrl[:] = c
            mujoco.mj_step(m, d)
            q.append(d.qpos.copy())
            v.append(d.qvel.copy())
        qp.append(q)
        qv.append(v)
        cs.append(ctrl)
    return np.array(qp), np.array(qv), np.array(cs)


@pytest.fixture(scope="module")
def logs():
    return robot_logs()


def test_a_user_mjcf_is_a_full_state_task_with_the_actuators_ranges():
    env = envs.from_mjcf(ARM, name="my_arm")
    assert env.name == "my_arm" and env.observation_size == 4 and env.action_size == 2
    ctrl = np.array([[8.0, -4.0], [0.0, 1.0]])
    np.testing.assert_allclose(env.ctrl_to_action(ctrl), [[1, -1], [0, 0.25]], atol=1e-7)
    np.testing.assert_allclose(env.action_to_ctrl(env.ctrl_to_action(ctrl)), ctrl, atol=1e-5)
    with pytest.raises(ValueError, match=r"ctrl\[1, 0\] = 9 is outside actuator 0's ctrlrange "
                                         r"\[-8, 8\]"):
        env.ctrl_to_action([[0.0, 0.0], [9.0, 0.0]])
    with pytest.raises(ValueError, match="observation='task' is for the registered tasks"):
        envs.from_mjcf(ARM, observation="task")


def test_sysid_identifies_a_user_mjcf_from_its_logs(logs):
    env = envs.from_mjcf(ARM, name="my_arm")
    res = sysid.fit(env, env.transitions(*logs),
                    sysid.SysidConfig(params=FITTED, max_latency=0))
    got = {r["parameter"]: r["identified"] for r in res.table}
    for name, truth in TRUTH.items():
        assert got[name] == pytest.approx(truth, rel=1e-3), (name, got[name], truth)
    # the massless frame is none of the defaults, and asking for it says why in one line
    assert "mass/tool_frame" not in sysid.config.default_param_names(env)
    with pytest.raises(ValueError, match=r"^parameter mass/tool_frame is 0 in the MJCF \(a "
                                         r"massless body.*cannot be fitted$"):
        sysid.fit(env, env.transitions(*logs),
                  sysid.SysidConfig(params=("mass/tool_frame",), max_latency=0))


def test_sysid_command_on_a_user_mjcf_and_an_npz_log(logs, tmp_path, capsys, monkeypatch):
    from twinrl import progress

    # progress is held back for 2 s, and a warm compilation cache fits in less (1.8 s in CI)
    monkeypatch.setattr(progress, "QUIET_FOR", 0.0)
    xml = tmp_path / "my_arm.xml"
    xml.write_text(ARM)
    log = tmp_path / "log.npz"
    qpos, qvel, ctrl = logs
    np.savez(log, qpos=qpos, qvel=qvel, ctrl=ctrl)
    args = ["sysid", "--env", str(xml), "--from", str(log), "--out", str(tmp_path / "s")]
    code = cli.main(args + [a for p in FITTED for a in ("--param", p)] + ["--max-latency", "0"])
    assert code == 0, capsys.readouterr().err
    # progress as lines (a log sees them): the compile, then the iterations
    out = capsys.readouterr().out
    assert "sysid my_arm [" in out and "compiling the windows' rollouts" in out
    assert "iteration 1: loss" in out
    table = {r["parameter"]: r["identified"] for r in
             json.loads((tmp_path / "s/summary.json").read_text())["table"]}
    for name, truth in TRUTH.items():
        assert table[name] == pytest.approx(truth, rel=1e-3), (name, table[name], truth)
    # the identified MJCF: MuJoCo compiles it to the fitted values (6 digits, MuJoCo's writer)
    m = mujoco.MjModel.from_xml_path(str(tmp_path / "s/identified.xml"))
    np.testing.assert_allclose(m.body_mass[1:], [TRUTH["mass/upper"], TRUTH["mass/fore"], 0.0],
                               rtol=1e-3)  # the tool frame stays massless
    np.testing.assert_allclose(m.dof_damping, [TRUTH["damping/shoulder"],
                                               TRUTH["damping/elbow"]], rtol=1e-3)
    nominal = mujoco.MjModel.from_xml_string(ARM)
    links = slice(1, 3)  # the massive bodies (the tool frame's 0 / 0 is no ratio)
    ratio = m.body_inertia[links] / nominal.body_inertia[links]  # scaled with the mass, as fitted
    np.testing.assert_allclose(ratio, np.repeat((m.body_mass[links] / nominal.body_mass[links])
                                                [:, None], 3, axis=1), rtol=1e-4)
    assert m.opt.timestep == nominal.opt.timestep and m.nu == 2
    np.savez(log, qpos=qpos, qvel=qvel[:, :-1], ctrl=ctrl)  # one state short
    assert cli.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "qvel" in err[0] and "(E, T + 1, 2)" in err[0], err


def test_a_log_without_an_array_or_no_npz_at_all_is_named(tmp_path):
    log = tmp_path / "log.npz"
    np.savez(log, qpos=np.zeros((1, 3, 2)), ctrl=np.zeros((1, 2, 2)))
    with pytest.raises(ValueError, match=r"^no qvel array \(it has qpos, ctrl\)$"):
        envs.mjcf.read_log(log)
    log.write_text("qpos,qvel,ctrl\n")
    with pytest.raises(ValueError, match=r"^not a readable \.npz"):
        envs.mjcf.read_log(log)
    qpos, qvel, ctrl = np.zeros((1, 3, 2)), np.ones((1, 3, 2)), np.zeros((1, 2, 2))
    np.savez(log, qpos=qpos, qvel=qvel, ctrl=ctrl)
    for got, want in zip(envs.mjcf.read_log(log), (qpos, qvel, ctrl)):
        np.testing.assert_array_equal(got, want)
