"""``twinrl.real.remote``: the real twin behind a process boundary.

Each route to the hidden truth that issue 22 names is tried from the learning side and must fail:
attribute access on the client (``_model``, ``_perturbation``, ``_renderer``, ``oracle``) and
anything reachable from it; a ``RealTwin`` in this process; ``Perturbation.sample`` with the
public seed. Evaluation, given the secret file, rebuilds the very twin the client drives. (That the
loop's inputs hold no evaluation output is ``tests/test_loop.py``'s
``test_the_loops_inputs_hold_no_evaluation_output``.)
"""

import gc
import json

import mujoco
import numpy as np
import pytest

from twinrl import eval as evaluation
from twinrl.real.perturbation import Perturbation
from twinrl.real.remote import TwinClient, hidden_perturbation
from twinrl.real.twin import RealTwin

TASK, SEED = "pendulum_swingup", 3


def _episode(env, steps=60):
    obs, _ = env.reset(seed=11)
    out = [obs]
    for t in range(steps):
        obs, *_ = env.step(np.array([0.8 * np.cos(0.2 * t)], np.float32))
        out.append(obs)
    return np.array(out)


def _twins_alive() -> int:
    """``RealTwin`` objects in this process. A dead ``weakref.proxy`` a library left in the heap
    raises ReferenceError when asked its type: it is no twin."""
    n = 0
    for o in gc.get_objects():
        try:
            n += isinstance(o, RealTwin)
        except ReferenceError:
            pass
    return n


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    secret = tmp_path_factory.mktemp("run") / "eval" / "twin.json"
    before = _twins_alive()
    client = TwinClient(TASK, seed=SEED, secret=secret, width=64, height=48)
    created_here = _twins_alive() - before
    traj = _episode(client)
    frames = client.render_images(client.camera, ("rgb", "depth"))
    yield client, secret, traj, frames, created_here
    client.close()


def _reachable(root, depth=4):
    """Every object reachable from ``root`` through instance dicts, containers and slots."""
    seen, todo, out = set(), [(root, 0)], []
    while todo:
        o, d = todo.pop()
        if id(o) in seen or d > depth:
            continue
        seen.add(id(o))
        out.append(o)
        children = []
        if isinstance(o, dict):
            children = list(o.keys()) + list(o.values())
        elif isinstance(o, (list, tuple, set, frozenset)):
            children = list(o)
        elif hasattr(o, "__dict__"):
            children = list(vars(o).values())
        todo += [(c, d + 1) for c in children]
    return out


def test_the_client_is_a_gymnasium_env_with_only_a_robots_interface(served):
    client, _, traj, frames, _ = served
    import gymnasium as gym

    assert isinstance(client, gym.Env) and client.task_name == TASK
    assert client.observation_space.shape == traj.shape[1:] and client.action_space.shape == (1,)
    assert frames["rgb"].shape == (48, 64, 3) and frames["depth"].shape == (48, 64)
    with pytest.raises(ValueError, match="finite numbers"):
        client.step(np.zeros(3))  # the server's own message; the server lives on
    assert client.step(np.zeros(1))[0].shape == traj.shape[1:]
    client.calibrate_controller(None)  # a robot without a Cartesian controller: nothing to set
    assert client.joint_speed is None
    with pytest.raises(ValueError, match="no Cartesian controller"):
        client.calibrate_controller(np.ones(7))


def test_no_model_perturbation_or_renderer_is_reachable_from_the_client(served):
    client, _, _, _, created_here = served
    for name in ("_model", "_perturbation", "_renderer", "_data", "oracle", "task",
                 "nominal_camera"):
        assert not hasattr(client, name), name
    hidden = (mujoco.MjModel, mujoco.MjData, Perturbation, RealTwin)
    leaks = [type(o).__name__ for o in _reachable(client) if isinstance(o, hidden)]
    assert not leaks, leaks
    assert created_here == 0, "a RealTwin was built in the client's process"


def test_only_a_robots_requests_are_served(served):
    client = served[0]
    call = client._TwinClient__call  # what a client could send over the pipe
    for op, args in (("oracle", ()), ("attr", ("_perturbation",)), ("__class__", ())):
        with pytest.raises(ValueError, match="no operation"):
            call(op, *args)
    assert client.camera_steps == 0 and client.mount_coords is None  # a task without a mount
    with pytest.raises(ValueError, match="no success measure"):
        client.success()


def test_the_public_seed_does_not_reproduce_the_hidden_perturbation(served):
    client, secret, traj, _, _ = served
    truth = hidden_perturbation(TASK, SEED, secret)
    # the public routes: the seed itself, and the draw RealTwin makes from it
    for guess in (Perturbation.sample(TASK, SEED),
                  Perturbation.sample(TASK, np.random.default_rng(
                      np.random.SeedSequence(SEED).spawn(2)[0]))):
        assert json.dumps(guess.__dict__, default=str) != json.dumps(truth.__dict__,
                                                                      default=str)
    public = RealTwin(TASK, seed=SEED, width=64, height=48)
    try:  # the public-seed twin behaves otherwise under the same actions
        assert not np.allclose(_episode(public), traj, atol=1e-3)
    finally:
        public.close()


def test_evaluation_rebuilds_the_served_twin_from_the_secret(served):
    client, secret, traj, _, _ = served
    twin = evaluation.rebuild_twin(TASK, SEED, secret=secret, width=64, height=48)
    try:
        np.testing.assert_allclose(_episode(twin), traj, rtol=0, atol=1e-6)
    finally:
        twin.close()


def test_each_secret_is_its_own_twin_and_a_resume_keeps_it(tmp_path, monkeypatch):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    # default: reproducible, the same (task, seed) meets the same twin; not the public-seed one
    pa, pb = hidden_perturbation(TASK, SEED, a), hidden_perturbation(TASK, SEED, b)
    assert json.loads(a.read_text())["salt"] == json.loads(b.read_text())["salt"]
    assert repr(pa) == repr(pb) != repr(Perturbation.sample(TASK, SEED))
    b.unlink()
    monkeypatch.setenv("TWINRL_TWIN_SALT", "random")
    pb = hidden_perturbation(TASK, SEED, b)
    assert json.loads(a.read_text())["salt"] != json.loads(b.read_text())["salt"]
    assert repr(pa) != repr(pb)
    monkeypatch.delenv("TWINRL_TWIN_SALT")
    assert repr(hidden_perturbation(TASK, SEED, a)) == repr(pa)  # read back, not redrawn
    with pytest.raises(ValueError, match="seed 3"):
        hidden_perturbation(TASK, SEED + 1, a)
    custom = Perturbation.none()
    c = tmp_path / "c.json"
    assert hidden_perturbation(TASK, SEED, c, custom) is custom
    with pytest.raises(ValueError, match="given"):
        hidden_perturbation(TASK, SEED, c, Perturbation.sample(TASK, 0))
