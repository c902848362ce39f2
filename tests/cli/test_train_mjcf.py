"""`twinrl train --env FILE.xml --reward FILE.py:FUNCTION`: learning in a user's own MJCF from the
shell, the checkpoint remembering the file and the reward so `twinrl eval` (sim and a real twin
of the MJCF) rebuilds the task; bad reward specs are one line, exit 2. The arm of
``tests/_turntable.py``; two PODS epochs (the test is the plumbing, learning is
``tests/envs/test_mjcf_reward.py``'s)."""

import json

import pytest

from tests._turntable import ARM
from tests.cli.test_bad_input import one_line_error, run

REWARD = '''import jax.numpy as jnp


def turn(qpos, qvel, action):
    return {"angle": -(qpos[0] - 1.0) ** 2, "effort": -0.01 * jnp.sum(action ** 2)}


def upright(qpos, qvel, action):
    return jnp.cos(qpos[0])


def vector(qpos, qvel, action):
    return qpos
'''

SMALL = ["--set", "batch_size=2", "--set", "rollout_length=20", "--set", "horizon=10",
         "--set", "eval_episodes=2", "--set", "eval_length=20", "--set", "hidden=[16]"]


@pytest.fixture
def files(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "arm.xml").write_text(ARM)
    (tmp_path / "rewards.py").write_text(REWARD)
    return tmp_path


def test_train_and_eval_a_users_mjcf(files, capsys):
    code, _, err = run(capsys, "train", "--env", "arm.xml", "--reward", "rewards.py:turn",
                       "--algo", "pods", "--epochs", "2", "--episode-length", "20",
                       "--frame-skip", "5", "--reset-noise", "0.3", *SMALL, "--out", "t")
    assert code == 0, err
    meta = json.loads((files / "t/policy/checkpoint.json").read_text())
    assert meta["mjcf"]["mjcf"] == str(files / "arm.xml")
    assert meta["mjcf"]["reward"] == f"{files / 'rewards.py'}:turn"
    assert meta["mjcf"]["config"] == {"episode_length": 20, "frame_skip": 5}
    assert meta["mjcf"]["reset_noise"] == 0.3
    for where in ([], ["--real"]):
        code, _, err = run(capsys, "eval", "--checkpoint", "t", "--episodes", "2",
                           "--no-video", *where, "--out", f"e{len(where)}")
        assert code == 0, err
        summary = json.loads((files / f"e{len(where)}/summary.json").read_text())
        assert len(summary["returns"]) == 2 and all(r < 0 for r in summary["returns"])
    # --resume with another reward is refused: run.json keeps the spec
    code, _, err = run(capsys, "train", "--env", "arm.xml", "--reward", "rewards.py:upright",
                       "--algo", "pods", "--epochs", "2", "--episode-length", "20",
                       "--frame-skip", "5", "--reset-noise", "0.3", *SMALL, "--resume",
                       "--out", "t")
    assert code == 2
    one_line_error(err, "--resume: ", "was started with different settings (mjcf)")


@pytest.mark.parametrize("reward, message", [
    (None, "--env arm.xml: an MJCF has no reward; give --reward FILE.py:FUNCTION"),
    ("rewards.py", "reward 'rewards.py': give FILE.py:FUNCTION or module:FUNCTION"),
    ("nothing.py:turn", "reward 'nothing.py:turn': no file nothing.py"),
    ("rewards.py:nope", "reward 'rewards.py:nope': rewards.py has no function nope"),
    ("rewards.py:vector", "reward term 'reward' must be a scalar, got shape (1,)"),
    ("no_such_module_x:f", "reward 'no_such_module_x:f': cannot import no_such_module_x"),
])
def test_bad_reward_specs_are_one_line(files, capsys, reward, message):
    args = ["train", "--env", "arm.xml", "--algo", "pods", "--out", "t"]
    code, _, err = run(capsys, *args, *(["--reward", reward] if reward else []))
    assert code == 2, err
    one_line_error(err, message)
    assert not (files / "t").exists()  # nothing written
