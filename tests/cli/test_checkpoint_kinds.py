"""Every kind of directory twinrl writes, given to every command that reads checkpoints
(``twinrl eval``, ``twinrl sense``, ``twinrl train --algo sensing --set actor=``; and ``twinrl
sysid --from``, which takes a dataset or a run): accepted, or
refused with exit 2 and one line naming what it is and the command that takes it.

The checkpoints are tiny (networks of 4 units) but real: written by ``save_policy``, the dataset
by ``DatasetWriter``, the run's layout as ``twinrl run`` leaves it. The accepted image actor is
run through ``twinrl eval`` in the simulator and on the real twin (3-step episodes), the state
policy through both too; a sensing Q's acceptance is its resolution (``sensing_q``), ``twinrl
sense`` itself being tested with a trained Q in ``tests/learn/test_sensing.py``.
"""

import json
import shutil

import jax
import numpy as np
import pytest

from twinrl import envs
from twinrl.cli import main
from twinrl.learn.checkpoint import read_meta, save_policy
from twinrl.learn.imitation import ImitationConfig, make_observer
from twinrl.learn.networks import NetworkConfig, make_network
from twinrl.loop.checkpoints import describe, sensing_q
from twinrl.real.dataset import DatasetWriter

ARM = "peg_insertion"
TINY = NetworkConfig(hidden=(4,), output="tanh")


def _save(path, spec, out_size, **meta):
    net = make_network(spec, out_size, TINY)
    return save_policy(path, net, net.init(jax.random.key(0)), **meta)


@pytest.fixture(scope="module")
def dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("kinds")
    arm = envs.make(ARM)
    _, actor_spec = make_observer(arm, ImitationConfig(observation="target"))
    m = arm.action_size
    pend = envs.make("pendulum_swingup")
    d = {}
    d["policy"] = _save(root / "policy", int(pend.observation_size), pend.action_size,
                        algo="pods", env="pendulum_swingup", env_config={"episode_length": 3})
    d["train"] = root / "train"
    shutil.copytree(d["policy"], d["train"] / "policy")
    (d["train"] / "run.json").write_text(json.dumps({"kind": "train", "algo": "pods"}))
    d["image_actor"] = _save(root / "actor", actor_spec, m, algo="imitation", env=ARM,
                             env_config={"episode_length": 3},
                             config={"observation": "target"})
    d["sensing_q"] = _save(root / "q", {**actor_spec, "action": (m,)}, 1, algo="sensing",
                           env=ARM, config={"actor": str(d["image_actor"])})
    obs_n = int(arm.observation_size)
    d["residual"] = _save(root / "residual", obs_n + m, m, kind="residual",
                          metrics={"accepted": False})
    d["hybrid_residual"] = _save(root / "hybrid", obs_n + m, obs_n, kind="hybrid_residual")
    # a manipulation run as `twinrl run` leaves it: settings, progress, a round's artefacts
    run = root / "run"
    run.mkdir()
    (run / "loop.json").write_text(json.dumps({"kind": "run", "env": ARM, "seed": 0,
                                               "config": {}}))
    (run / "progress.json").write_text(json.dumps({"done": [], "rounds": {}}))
    r1 = run / "round1"
    r1.mkdir()
    (r1 / "round.json").write_text(json.dumps({"kind": "round", "round": 1}))
    for name, src in (("actor", "image_actor"), ("q", "sensing_q"), ("residual", "residual"),
                      ("hybrid", "hybrid_residual")):
        shutil.copytree(d[src], r1 / name / ("policy" if name in ("actor", "q") else ""),
                        dirs_exist_ok=True)
    d["run"], d["round"] = run, r1
    d["round_q"], d["round_residual"] = r1 / "q", r1 / "residual"
    # a cartpole-family run (no Q)
    cart = root / "cartrun"
    cart.mkdir()
    (cart / "loop.json").write_text(json.dumps({"kind": "run", "env": "cartpole_swingup",
                                                "seed": 0, "config": {}}))
    (cart / "progress.json").write_text(json.dumps({"done": [], "rounds": {}}))
    d["cartrun"] = cart
    with DatasetWriter(root / "dataset", env=ARM, obs_shape=3, action_shape=1) as w:
        w.add(np.zeros(3), np.zeros(1), 0.0, np.zeros(3), False, True)
    d["dataset"] = root / "dataset"
    for kind in ("sense", "eval"):
        (root / kind).mkdir()
        (root / kind / "summary.json").write_text(json.dumps({"kind": kind, "env": ARM}))
        d[kind] = root / kind
    return d


def test_each_directory_says_what_it_is(dirs):
    want = {"policy": "policy", "train": "policy", "image_actor": "image_actor",
            "sensing_q": "sensing_q", "residual": "residual",
            "hybrid_residual": "hybrid_residual", "run": "run", "round": "round",
            "round_q": "sensing_q", "round_residual": "residual", "cartrun": "run",
            "dataset": "dataset", "sense": "sense", "eval": "eval"}
    assert {k: describe(dirs[k]).kind for k in want} == want
    # the kind is written into checkpoint.json, not only told from the layout
    for k in ("policy", "image_actor", "sensing_q", "residual", "hybrid_residual"):
        assert json.loads((dirs[k] / "checkpoint.json").read_text())["kind"] == k
    assert describe(dirs["round_q"]).round.path == dirs["round"]
    assert describe(dirs["run"]).run.out == dirs["run"]


def test_a_checkpoint_written_before_kinds_is_told_by_its_algorithm(dirs, tmp_path):
    for src, kind in (("sensing_q", "sensing_q"), ("image_actor", "image_actor"),
                      ("policy", "policy")):
        old = tmp_path / src
        shutil.copytree(dirs[src], old)
        meta = json.loads((old / "checkpoint.json").read_text())
        del meta["kind"]
        (old / "checkpoint.json").write_text(json.dumps(meta))
        assert read_meta(old)[1]["kind"] == kind


REFUSED = [
    # (command, kind, words the one line must hold: the command that takes it)
    ("eval", "sensing_q", "twinrl sense --env peg_insertion --checkpoint"),
    ("eval", "round_q", "twinrl sense --env peg_insertion --checkpoint"),
    ("eval", "residual", "twinrl eval --checkpoint ROUND"),
    ("eval", "round_residual", "evaluates the round with it"),
    ("eval", "hybrid_residual", "not a policy"),
    ("eval", "dataset", "twinrl sysid --env peg_insertion --from"),
    ("eval", "sense", "holds no checkpoint"),
    ("eval", "eval", "holds no checkpoint"),
    ("sense", "policy", "twinrl eval --checkpoint"),
    ("sense", "train", "twinrl eval --checkpoint"),
    ("sense", "image_actor", "twinrl eval --checkpoint"),
    ("sense", "residual", "evaluates the round"),
    ("sense", "hybrid_residual", "not a policy"),
    ("sense", "cartrun", "has no sensing-aware Q"),
    ("sense", "dataset", "twinrl sysid"),
    ("sense", "sense", "holds no checkpoint"),
    ("sense", "eval", "holds no checkpoint"),
    ("actor", "policy", "not an image actor"),
    ("actor", "sensing_q", "not an image actor"),
    ("actor", "residual", "not an image actor"),
    ("actor", "hybrid_residual", "not an image actor"),
    ("sysid", "image_actor", "twinrl eval --checkpoint"),
    ("sysid", "sensing_q", "twinrl sense --env peg_insertion"),
    ("sysid", "sense", "holds no checkpoint"),
]


def _argv(command, path, out):
    if command == "eval":
        return ["eval", "--checkpoint", str(path), "--out", str(out), "--episodes", "1"]
    if command == "sense":
        return ["sense", "--env", ARM, "--checkpoint", str(path), "--out", str(out)]
    if command == "sysid":
        return ["sysid", "--env", ARM, "--from", str(path), "--out", str(out)]
    return ["train", "--env", ARM, "--algo", "sensing", "--set", f'actor="{path}"', "--out",
            str(out)]


@pytest.mark.parametrize("command,kind,words", REFUSED)
def test_a_kind_a_command_cannot_use_is_one_line_naming_the_one_that_can(
        dirs, tmp_path, capsys, command, kind, words):
    assert main(_argv(command, dirs[kind], tmp_path / "out")) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert words in err, err
    assert not (tmp_path / "out" / "summary.json").exists()


def test_sense_takes_a_q_its_training_run_a_round_or_a_run(dirs):
    q = dirs["sensing_q"]
    assert sensing_q(q) == q
    assert sensing_q(dirs["round_q"]) == dirs["round_q"] / "policy"
    assert sensing_q(dirs["round"]) == dirs["round"] / "q"
    assert sensing_q(dirs["run"]) == dirs["round"] / "q"


def test_eval_runs_a_state_policy_and_refuses_actor_options_for_it(dirs, tmp_path, capsys):
    assert main(["eval", "--checkpoint", str(dirs["train"]), "--episodes", "2", "--no-video",
                 "--out", str(tmp_path / "sim")]) == 0
    s = json.loads((tmp_path / "sim" / "summary.json").read_text())
    assert s["kind"] == "eval" and len(s["returns"]) == 2 and s["where"] == "sim"
    assert main(["eval", "--checkpoint", str(dirs["policy"]), "--camera", "chosen",
                 "--out", str(tmp_path / "x")]) == 2
    assert "--camera: for an arm task's image actor" in capsys.readouterr().err


@pytest.mark.parametrize("real", [False, True], ids=["sim", "real"])
def test_eval_deploys_an_image_actor(dirs, tmp_path, capsys, real):
    out = tmp_path / "out"
    argv = ["eval", "--checkpoint", str(dirs["image_actor"]), "--camera", "random",
            "--episodes", "2", "--out", str(out)] + (["--real"] if real else [])
    assert main(argv) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["where"] == ("real twin" if real else "sim") and s["camera"] == "random"
    assert s["episodes"] == 2 and len(s["successes"]) == 2 and len(s["returns"]) == 2
    lo, hi = s["success_interval_95"]
    assert 0.0 <= lo <= s["success_rate"] <= hi <= 1.0 and hi - lo > 0.5  # 2 episodes
    coords = np.asarray(s["camera_coords"])
    assert coords.shape == (2, 3) and not np.allclose(coords[0], coords[1])  # drawn per episode
    assert (out / ("real.mp4" if real else "sim.mp4")).exists()
    # --camera chosen needs a Q: none beside a lone actor
    assert main(argv[:4] + ["chosen", "--no-video", "--out", str(tmp_path / "q")]) == 2
    assert "--camera chosen needs a sensing-aware Q" in capsys.readouterr().err


def test_eval_of_a_cartpole_family_round_deploys_its_accepted_residual(dirs, tmp_path):
    # pi_sim and an accepted residual, as the cartpole loop leaves them in round<r>/
    run = tmp_path / "run"
    r1 = run / "round1"
    r1.mkdir(parents=True)
    (run / "loop.json").write_text(json.dumps({"kind": "run", "env": "pendulum_swingup",
                                               "seed": 0, "config": {}}))
    (run / "progress.json").write_text(json.dumps({"done": [], "rounds": {}}))
    shutil.copytree(dirs["train"], r1 / "train")
    pend = envs.make("pendulum_swingup")
    n, m = int(pend.observation_size), pend.action_size
    _save(r1 / "residual", n + m, m, kind="residual", metrics={"accepted": True})
    got = {}
    for flags in ([], ["--no-residual"]):
        out = tmp_path / f"out{len(flags)}"
        assert main(["eval", "--checkpoint", str(run), "--episodes", "2", "--no-video",
                     "--out", str(out)] + flags) == 0
        s = json.loads((out / "summary.json").read_text())
        got[s["residual"]] = s["returns"]
    assert set(got) == {True, False}
    assert not np.allclose(got[True], got[False])  # the correction changes what it does
