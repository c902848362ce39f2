"""MuJoCo's C warnings reach the user as Python warnings, and no MUJOCO_LOG.TXT is written."""

import warnings

import mujoco
import numpy as np
import pytest

from twinrl.physics import MJCFError, MuJoCoWarning, load_mjcf, mujoco_warnings

# a deprecated compiler attribute MuJoCo still accepts, with a warning (Gymnasium's half_cheetah)
DEPRECATED = """<mujoco><compiler settotalmass="2"/><worldbody><body><freejoint/>
<geom type="sphere" size="0.1"/></body></worldbody></mujoco>"""


@pytest.fixture
def cwd(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.fixture
def no_handler():
    """MuJoCo's own warning handler (none) for the test; whatever another test's import set
    (dm_control installs one) is put back afterwards."""
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(None)
    yield
    mujoco.set_mju_user_warning(previous)


def test_compile_warning_is_a_python_warning_and_no_log_file(cwd, no_handler):
    path = cwd / "deprecated.xml"
    path.write_text(DEPRECATED)
    with pytest.warns(MuJoCoWarning, match=r"deprecated\.xml: MuJoCo: .*settotalmass"):
        model = load_mjcf(path)
    with pytest.warns(MuJoCoWarning, match=r"the MJCF string: MuJoCo: .*settotalmass"):
        load_mjcf(DEPRECATED)
    assert model.body_mass[1] == pytest.approx(2.0)  # the model is still compiled
    assert list(cwd.iterdir()) == [path]
    assert mujoco.get_mju_user_warning() is None  # MuJoCo's own handler is back


def test_spec_compile_warnings_are_mujoco_warnings_too(cwd):
    # MjSpec.compile raises MuJoCo's warnings as plain UserWarnings; other categories pass
    with pytest.warns(MuJoCoWarning, match=r"spec: MuJoCo: .*settotalmass"):
        with pytest.warns(DeprecationWarning, match="mine"):
            with mujoco_warnings("spec"):
                mujoco.MjSpec.from_string(DEPRECATED).compile()
                warnings.warn("mine", DeprecationWarning)
    assert list(cwd.iterdir()) == []


def test_unstable_step_warns_once_and_writes_nothing(cwd):
    model = load_mjcf(DEPRECATED.replace('<compiler settotalmass="2"/>', ""))
    data = mujoco.MjData(model)
    with pytest.warns(MuJoCoWarning, match="Nan, Inf or huge value") as got:
        with mujoco_warnings("unstable"):
            for _ in range(3):
                data.qvel[:] = 1e20
                mujoco.mj_step(model, data)
    assert len([w for w in got if issubclass(w.category, MuJoCoWarning)]) == 1
    assert list(cwd.iterdir()) == []


def test_callers_handler_is_restored_and_errors_still_raise(cwd):
    mine: list[str] = []
    mujoco.set_mju_user_warning(mine.append)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", MuJoCoWarning)
            load_mjcf(DEPRECATED)
        assert mine == []  # inside the block twinrl's handler took it
        assert mujoco.get_mju_user_warning() is not None
        mujoco.MjModel.from_xml_string(DEPRECATED)  # outside it, the caller's handler
        assert len(mine) == 1 and "settotalmass" in mine[0]
    finally:
        mujoco.set_mju_user_warning(None)
    with pytest.raises(MJCFError, match="malformed MJCF string"):
        load_mjcf("<mujoco><worldbody><geom/></worldbody>")
    assert mujoco.get_mju_user_warning() is None


def test_cli_prints_mujoco_warnings_on_one_line():
    from twinrl import cli

    before = warnings.formatwarning
    try:
        cli.one_line_warnings("twinrl gradcheck")
        text = warnings.formatwarning(MuJoCoWarning("x.xml: MuJoCo: old"), MuJoCoWarning,
                                      "sim.py", 61)
        other = warnings.formatwarning(UserWarning("y"), UserWarning, "sim.py", 61)
    finally:
        warnings.formatwarning = before
    assert text == "twinrl gradcheck: warning: x.xml: MuJoCo: old\n"
    assert other.startswith("sim.py:61: UserWarning: y")


def test_real_twin_step_routes_warnings(cwd):
    from twinrl import real

    twin = real.make_real("pendulum_swingup", seed=0)
    twin.reset(seed=0)
    twin._data.qvel[:] = np.inf  # an unstable state, as a diverging real system gives
    with pytest.warns(MuJoCoWarning, match="pendulum_swingup real twin: MuJoCo: Nan, Inf"):
        twin.step(np.zeros(twin.action_space.shape, np.float32))
    assert list(cwd.iterdir()) == []
