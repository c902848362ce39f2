"""Bad input to the ``twinrl`` command gets one clear line and exit status 2 (or the right
behaviour), never a traceback. Run in process (``cli.main``): these fail before any compile."""

import errno
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from twinrl import cli
from twinrl.real.dataset import read


def run(capsys, *args):
    code = cli.main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def one_line_error(err, *fragments):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for f in fragments:
        assert f in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize("args, message", [
    (["gradcheck", "/no/such/robot.xml"], "MJCF file not found: /no/such/robot.xml"),
    (["gradcheck", "nosuchscene"], "unknown scene 'nosuchscene'"),
    (["gradcheck", "pendulum", "--entries", "0"], "--entries must be >= 1, got 0"),
    (["gradcheck", "pendulum", "--step", "-1"], "--step must be > 0, got -1.0"),
    (["collect", "--env", "nosuchtask", "--episodes", "1"], "unknown task 'nosuchtask'"),
    (["collect", "--env", "pendulum_swingup", "--episodes", "0"], "--episodes must be >= 1"),
    (["sysid", "--env", "cartpole_swingup", "--from", "/no/such/data"],
     "--from /no/such/data: no dataset there"),
    (["train", "--env", "pendulum_swingup", "--algo", "shac", "--set", "no_such_field=1"],
     "SHACConfig has no field 'no_such_field'"),
    (["train", "--env", "pendulum_swingup", "--algo", "ppo", "--epochs", "3"],
     "--epochs does not apply to PPOConfig"),
    (["eval", "--checkpoint", "/no/such/ckpt"], "checkpoint /no/such/ckpt does not exist"),
    (["eval", "--checkpoint", ".", "--episodes", "0"], "--episodes must be >= 1, got 0"),
    (["eval", "--checkpoint", ".", "--size", "0", "240"], "--size 0 240: width and height"),
    (["render", "--env", "push", "--steps", "0"], "--steps must be >= 1, got 0"),
    (["render", "--env", "push", "--size", "320", "-1"], "--size 320 -1: width and height"),
    (["render", "--env", "push", "--size", "5000", "5000", "--steps", "1"],
     "image size 5000x5000 must be positive and within the model's offscreen buffer"),
    (["render", "--env", "push", "--gradcheck"], "--gradcheck is for your MJCF"),
    (["render", "--env", "push", "--camera", "nosuch", "--steps", "1"],
     "camera 'nosuch' is not in the scene"),
    (["run", "--env", "cartpole_swingup", "--rounds", "0"], "rounds must be >= 1"),
    (["run", "--env", "peg_insertion", "--set", "foo=1"],
     "the manipulation loop has no setting 'foo'"),
    (["run", "--env", "peg_insertion", "--set", "imitation.observation=state"],
     "the loop deploys an image actor"),
    (["run", "--env", "peg_insertion", "--algo", "shac"], "--algo is the state-based loop's"),
    (["run", "--env", "push"], "push's observation does not determine its state"),
    (["train", "--env", "my_robot.xml", "--algo", "pods"], "--env my_robot.xml: no such MJCF file"),
    (["train", "--env", "pendulum_swingup", "--algo", "pods", "--set", "horizon=500"],
     "PODSConfig on pendulum_swingup: horizon (500) must be <= the rollout length (250)"),
    (["train", "--env", "push", "--algo", "pods", "--reward", "r.py:f"],
     "--reward: for your MJCF (--env FILE.xml); task 'push' has its own"),
    (["run", "--env", "my_robot.xml"], "the loop is for the registered tasks"),
])
def test_bad_input_gets_one_clear_line(args, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code, _, err = run(capsys, *args)
    assert code == 2, err
    one_line_error(err, message)


def test_collect_again_appends_new_episodes_not_copies(tmp_path, capsys):
    for _ in range(2):
        code, _, err = run(capsys, "collect", "--env", "pendulum_swingup", "--episodes", "1",
                           "--out", tmp_path)
        assert code == 0, err
    ds = read(tmp_path / "dataset")
    first, second = list(ds.episodes())
    assert (first.id, second.id) == (0, 1) and first.complete and second.complete
    assert not np.array_equal(first.obs[0], second.obs[0])      # another initial state
    assert not np.array_equal(first.action, second.action)      # another excitation
    # the episode with id i is the same whether recorded in one run or appended by a second
    # (on the same twin: its hidden perturbation's secret salt copied over, as a run with
    # TWINRL_TWIN_SALT=random would need; by default the salt is seeded, twinrl.real.remote)
    import shutil

    shutil.copytree(tmp_path / "eval", tmp_path / "once" / "eval")
    code, _, err = run(capsys, "collect", "--env", "pendulum_swingup", "--episodes", "2",
                       "--out", tmp_path / "once")
    assert code == 0, err
    once = list(read(tmp_path / "once/dataset").episodes())
    assert np.array_equal(once[1].obs, second.obs) and np.array_equal(once[1].action,
                                                                      second.action)


def test_collect_into_a_dataset_another_process_writes_is_refused(tmp_path, capsys):
    code, _, err = run(capsys, "collect", "--env", "pendulum_swingup", "--episodes", "1",
                       "--out", tmp_path)
    assert code == 0, err
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, os, sys, time; "
         "fd = os.open(sys.argv[1], os.O_RDWR); fcntl.flock(fd, fcntl.LOCK_EX); "
         "print('locked', flush=True); time.sleep(120)", str(tmp_path / "dataset/.lock")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        code, _, err = run(capsys, "collect", "--env", "pendulum_swingup", "--episodes", "1",
                           "--out", tmp_path)
    finally:
        holder.kill()
        holder.wait()
    assert code == 2
    one_line_error(err, "twinrl collect: error:", "is being written by another DatasetWriter")
    assert read(tmp_path / "dataset").num_episodes == 1


def test_collect_of_another_env_into_a_dataset_is_refused(tmp_path, capsys):
    code, _, err = run(capsys, "collect", "--env", "pendulum_swingup", "--episodes", "1",
                       "--out", tmp_path)
    assert code == 0, err
    code, _, err = run(capsys, "collect", "--env", "cartpole_swingup", "--episodes", "1",
                       "--out", tmp_path)
    assert code == 2
    one_line_error(err, "env='cartpole_swingup' does not match 'pendulum_swingup'")
    assert read(tmp_path / "dataset").num_episodes == 1


def test_push_collects_full_states_for_sysid_and_refuses_its_task_observation(tmp_path, capsys):
    """push's observation (planar) does not determine its state: sysid on it is one line
    naming the fix, before any work; ``collect --observation state`` records qpos and qvel with
    the task's closed-loop excitation (its strokes move the box), and a dataset keeps one
    layout."""
    from twinrl import envs

    code, _, err = run(capsys, "collect", "--env", "push", "--episodes", "1", "--out",
                       tmp_path / "task")
    assert code == 0, err
    code, _, err = run(capsys, "sysid", "--env", "push", "--from", tmp_path / "task",
                       "--out", tmp_path / "s")
    assert code == 2
    one_line_error(err, "push's observation does not determine its state",
                   "twinrl collect --env push --observation state")
    code, _, err = run(capsys, "collect", "--env", "push", "--episodes", "1", "--observation",
                       "state", "--out", tmp_path / "full")
    assert code == 0, err
    ds = read(tmp_path / "full/dataset")
    sim = envs.make("push").sim
    assert ds.meta["metadata"] == {"observation": "state"}
    assert ds.obs.shape[1:] == (sim.nq + sim.nv,)
    box = ds.obs[:, 2:4]  # the box's planar position (qpos[2:4]): the strokes push it
    assert np.ptp(box, axis=0).max() > 0.02, np.ptp(box, axis=0)
    code, _, err = run(capsys, "collect", "--env", "push", "--episodes", "1", "--out",
                       tmp_path / "full")
    assert code == 2 and read(tmp_path / "full/dataset").num_episodes == 1
    one_line_error(err, "twinrl collect: error:")


def test_collect_with_an_image_size_the_renderer_refuses_writes_nothing(tmp_path, capsys):
    code, _, err = run(capsys, "collect", "--env", "pendulum_swingup", "--episodes", "1",
                       "--images", "--size", "4000", "4000", "--out", tmp_path / "c")
    assert code == 2
    one_line_error(err, "--size 4000 4000:", "offscreen buffer 640x480")
    assert not (tmp_path / "c").exists()  # no meta.json claiming 4000x4000 images


def test_disk_full_during_collect_is_one_line_and_the_dataset_stays_readable(
        tmp_path, capsys, monkeypatch):
    real_write, calls = os.write, []

    def write(fd, data):  # the disk fills up after 100 records of the second episode's run
        if "chunk-" in os.readlink(f"/proc/self/fd/{fd}"):
            calls.append(fd)
            if len(calls) > 100:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(fd, data)

    code, _, err = run(capsys, "collect", "--env", "pendulum_swingup", "--episodes", "1",
                       "--out", tmp_path)
    assert code == 0, err
    monkeypatch.setattr(os, "write", write)
    code, _, err = run(capsys, "collect", "--env", "pendulum_swingup", "--episodes", "2",
                       "--out", tmp_path)
    monkeypatch.undo()
    assert code == 2
    one_line_error(err, "No space left on device", "the dataset keeps every transition")
    ds = read(tmp_path / "dataset")  # strict: no damage, only an episode cut short
    assert ds.problems == [] and ds.num_episodes == 2
    assert list(ds.episode_complete) == [True, False] and len(ds) == 250 + 99


@pytest.mark.parametrize("doc, message", [
    ([1, 2], "holds a JSON list, expected an object"),
    ({"format": "twinrl.policy/1", "env": "pendulum_swingup"}, "no 'network' object"),
])
def test_eval_of_a_malformed_checkpoint_json_is_one_line(tmp_path, capsys, doc, message):
    from twinrl.learn.checkpoint import FORMAT

    if isinstance(doc, dict):
        doc["format"] = FORMAT
    (tmp_path / "checkpoint.json").write_text(json.dumps(doc))
    code, _, err = run(capsys, "eval", "--checkpoint", tmp_path, "--out", tmp_path / "e")
    assert code == 2
    one_line_error(err, "twinrl eval: error:", str(tmp_path / "checkpoint.json"), message)


def test_gradcheck_of_a_model_with_a_massless_mount_runs(tmp_path, capsys):
    """A body without dofs and without mass (a mount) is a valid MJCF: checked, not refused."""
    mjcf = tmp_path / "arm.xml"
    mjcf.write_text("""<mujoco><worldbody><body name="mount" pos="0 0 1">
        <body name="link"><joint type="hinge"/><geom size="0.1" pos="0.2 0 0"/></body>
        </body></worldbody></mujoco>""")
    code, out, _ = run(capsys, "gradcheck", mjcf, "--horizon", "2", "--out", tmp_path / "g")
    summary = json.loads((tmp_path / "g" / "summary.json").read_text())
    assert code == 0 and summary["nan_count"] == 0 and summary["failures"] == 0
    # gravity is unjudged over 2 float32 steps, and not for the forward's roughness: no reason
    # is given that does not hold
    assert summary["unjudged"] == ["params.gravity"] and summary["loss_jitter"] >= 0
    assert "not judged (no resolved entry): params.gravity" in out
    assert "moved the loss" not in out


def test_gradcheck_says_when_the_forwards_roughness_leaves_a_group_unjudged():
    # a resting flat box (measured: the loss moves 1.9e-10 beyond its gradient on an ulp-sized
    # move; mass's derivative 1e-4): differences at 1e-6 resolve nothing below ~19
    from twinrl.physics.gradcheck import GradcheckResult

    def result(loss_jitter):
        groups = [{"group": "params.mass", "resolved": 0, "inert": False, "max_abs_grad": 1e-4},
                  {"group": "qvel", "resolved": 2, "inert": False, "max_abs_grad": 3.6}]
        return GradcheckResult(scene="box", horizon=30, dtype="float64", rtol=1e-4, rows=[],
                               groups=groups, constrained_steps=24, free_steps=6,
                               loss_jitter=loss_jitter, step=1e-6)

    line = cli.unjudged_line(result(1.9e-10))
    assert line.startswith("not judged (no resolved entry): params.mass; ") and "\n" not in line
    assert "moved the loss by 1.9e-10" in line and "below ~1.9e+01" in line
    # where the roughness would allow the derivative, it is not given as the reason
    assert cli.unjudged_line(result(1e-17)) == (
        "not judged (no resolved entry): params.mass")


def test_gradcheck_of_an_empty_path_says_it_is_empty(tmp_path, capsys):
    code, _, err = run(capsys, "gradcheck", "", "--out", tmp_path / "g")
    assert code == 2
    one_line_error(err, "the MJCF path is empty")


def test_sysid_reads_past_a_damaged_chunk_saying_what_was_dropped(tmp_path, capsys, monkeypatch):
    from twinrl.real2sim import sysid

    code, _, err = run(capsys, "collect", "--env", "pendulum_swingup", "--episodes", "1",
                       "--out", tmp_path)
    assert code == 0, err
    (chunk,) = (tmp_path / "dataset").glob("chunk-*.twr")
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    seen = []

    def fit(env, data, config, **kwargs):  # stands in for the fit: what it was given matters
        seen.append(len(data))
        raise ValueError("stop here")

    monkeypatch.setattr(sysid, "fit", fit)
    code, _, err = run(capsys, "sysid", "--env", "pendulum_swingup", "--from", tmp_path,
                       "--out", tmp_path / "s")
    assert seen == [249] and code == 2, err
    warning, error = err.strip().splitlines()
    assert warning.startswith("twinrl sysid: warning: dataset damaged, using its 249 intact")
    assert str(chunk) in warning and error == "twinrl sysid: error: stop here"
