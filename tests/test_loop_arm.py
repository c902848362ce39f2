"""``twinrl.loop.arm`` (the SAM-RL loop on a manipulation task): a run killed with SIGKILL in the
middle of a real deployment episode and resumed keeps every real transition and frame it had
recorded, does not redo finished stages, re-runs the cut episode from its start (the same episode:
the same reset seed, the same first transitions), and ends with every round's episodes complete.

The stages that compile for minutes (the calibration's fit, trajopt, imitation) are replaced in the
child process by cheap stand-ins (the nominal camera, zero plans, a seeded random target-cloud
actor saved as a policy checkpoint); the deployment is the real one (``Deployer`` on the real
twin's server, the actor acting on the real mount frames, the fixed default camera), slowed a few
milliseconds a step so the kill lands inside an episode. Each real stage has its own tests.
"""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from twinrl.real import dataset as ds

K = 2
T = 50  # the arm tasks' episode length

CHILD = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    import jax, numpy as np
    from twinrl import report
    from twinrl.loop import arm as loop_arm
    from twinrl.learn import plans
    from twinrl.learn.checkpoint import save_policy
    from twinrl.learn.imitation import ImitationConfig, make_observer
    from twinrl.learn.networks import NetworkConfig, make_network
    from twinrl.sim2real import active

    out, resume = Path(sys.argv[1]), sys.argv[2] == "resume"
    log = out.parent / "calls.log"

    def note(s):
        with open(log, "a") as f:
            f.write(s + "\\n")

    def calibrate(run, r, rdir, data):
        note(f"calibrate {len(data)}")
        env = run.nominal_env
        cam = env.mount.camera(np.asarray(env.mount.default, np.float32), 64, 64)
        report.write_json(rdir.calibration, {"camera": {
            "pos": np.asarray(cam.pos), "quat": np.asarray(cam.quat),
            "fovy": np.asarray(cam.fovy), "width": 64, "height": 64}})
        run.prog.mark(f"round{r}/calibrate")

    def plan(run, r, rdir, env):
        note("plan")
        T, m = env.episode_length, env.action_size
        plans.save(rdir.plans, {"plans": np.zeros((2, T, m), np.float32),
                                        "keys": np.zeros((2, 2), np.uint32),
                                        "success": np.ones(2)})
        run.prog.mark(f"round{r}/plan", plan_success=1.0)

    def imitate(run, r, rdir, env):
        note("imitation")
        cfg = ImitationConfig(observation="target")
        _, spec = make_observer(env, cfg)
        net = make_network(spec, env.action_size, NetworkConfig(hidden=(8,), output="tanh"))
        params = net.init(jax.random.key(r))
        save_policy(rdir.actor / "policy", net, params, algo="imitation", env=env.name,
                    config=cfg)
        run.prog.mark(f"round{r}/imitation", sim_success=0.0)

    stages = {"calibrate": calibrate, "plan": plan, "imitation": imitate}
    loop_arm.ARM_ROUND = tuple(s.__class__(s.name, s.needs, s.gives, stages.get(s.name, s.make),
                                           s.load, s.enabled) for s in loop_arm.ARM_ROUND)
    real_act = active.Deployer.__init__

    def slow_init(self, *a, **k):
        real_act(self, *a, **k)
        act = self._act
        def slow(p, o):
            time.sleep(0.01)
            with open(out.parent / "acts.log", "a") as f:  # the parent times its kill by it
                f.write("a")
            return act(p, o)
        self._act = slow
    active.Deployer.__init__ = slow_init

    # no sysid: minutes of float64 arm rollouts, and resume is the same for every stage
    config = loop_arm.ArmLoopConfig(rounds=1, episodes_per_round=%d, camera="default",
                                    eval_episodes=0, video=True, sysid=False)
    note("start resume" if resume else "start")
    loop_arm.run("peg_insertion", out, config, seed=2, resume=resume, progress=False)
    note("finished")
""" % K)


def _child(out: Path, mode: str):
    return subprocess.Popen([sys.executable, "-c", CHILD, str(out), mode],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _progress(out: Path) -> dict:
    try:
        return json.loads((out / "progress.json").read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return {"done": [], "rounds": {}}


@pytest.fixture(scope="module")
def killed(tmp_path_factory):
    out = tmp_path_factory.mktemp("loop_arm") / "run"
    out.parent.joinpath("x").mkdir()
    p = _child(out, "fresh")
    deadline = time.time() + 600
    acts = out.parent / "acts.log"
    # wait for the first deployed episode to be recorded, then for the second to have acted a
    # few steps (each act is logged before its step): a fixed sleep missed it on a loaded machine
    while time.time() < deadline and "round1/deploy_partial" not in _progress(out)["done"]:
        assert p.poll() is None, p.communicate()[0]
        time.sleep(0.02)
    while time.time() < deadline and (acts.stat().st_size if acts.exists() else 0) < T + 4:
        assert p.poll() is None, p.communicate()[0]
        time.sleep(0.01)
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    at_kill = ds.read(out / "dataset")
    progress_at_kill = _progress(out)
    p = _child(out, "resume")
    text, _ = p.communicate(timeout=600)
    assert p.returncode == 0, text
    return out, at_kill, progress_at_kill


def test_killed_inside_the_second_deployed_episode(killed):
    _, at_kill, prog = killed
    assert "round1/deploy" not in prog["done"] and "round1/imitation" in prog["done"]
    assert prog["rounds"]["round1"]["deploy_episodes"] == 1  # the rows: round1/deploy_partial.json
    # round 0's K episodes and one deployed episode complete, the next one cut short
    assert int(np.sum(at_kill.episode_complete)) == K + 1
    assert (K + 1) * T < len(at_kill) < (K + 2) * T


def test_resume_keeps_every_recorded_transition_and_frame(killed):
    out, at_kill, _ = killed
    final = ds.read(out / "dataset")
    n = len(at_kill)
    for name in ("obs", "action", "reward", "next_obs", "episode_id"):
        np.testing.assert_array_equal(getattr(final, name)[:n], getattr(at_kill, name)[:n])
    for kind in ("rgb", "depth", "segmentation"):
        np.testing.assert_array_equal(final.images[kind][:n], at_kill.images[kind][:n])
    # every round's episodes complete, plus the cut one kept as incomplete
    assert int(np.sum(final.episode_complete)) == 2 * K
    assert len(final.episode_complete) == 2 * K + 1
    assert len(final) == 2 * K * T + (n - (K + 1) * T)


def test_the_cut_episode_is_run_again_from_its_start(killed):
    out, at_kill, _ = killed
    final = ds.read(out / "dataset")
    cut = final.episode_id == final.episode_id[len(at_kill) - 1]
    rerun = final.episode_id == final.episode_id[-1]
    m = int(cut.sum())
    # the same reset seed and a deterministic actor on the same frames: the same transitions
    np.testing.assert_allclose(final.obs[rerun][:m], final.obs[cut], atol=1e-6)
    np.testing.assert_allclose(final.action[rerun][:m], final.action[cut], atol=1e-6)


def test_finished_stages_are_not_redone_and_the_summary_counts_the_episodes(killed):
    out, _, _ = killed
    calls = (out.parent / "calls.log").read_text().split("\n")
    assert calls.count("plan") == calls.count("imitation") == 1, calls
    assert calls.index("start resume") > calls.index("imitation")
    s = json.loads((out / "summary.json").read_text())
    r1 = s["rounds"][1]
    assert len(r1["real_successes"]) == K and r1["camera_steps"] == 0  # the fixed camera
    assert r1["deployed_camera"] == "default"  # what the table, plot and video name
    assert r1["real_steps"] == len(ds.read(out / "dataset"))
    assert (out / "success.png").exists()
    # the outputs after the resume: the report, the actor's saliency (no Q with the default
    # camera: the default view's), and the video of one more episode
    report = (out / "report.md").read_text()
    assert report.startswith("# twinrl run: peg_insertion (seed 2)") and "**Verdict:**" in report
    assert "](sense/saliency.png)" in report and (out / "sense" / "saliency.png").exists()
    assert s["figures"] == {"saliency": str(out / "sense" / "saliency.png")}
    # drawn at the start of the last deployed episode, from the pose it was deployed with
    fig = json.loads((out / "sense" / "summary.json").read_text())
    assert "last deployed episode" in fig["state"] and fig["deployed_camera"] == "default"
    assert fig["coords"] == {"default": r1["chosen_coords"][-1]}
    assert (out / "final.mp4").stat().st_size > 0 and s["video"] == str(out / "final.mp4")


def test_bad_settings_fail_with_one_line(tmp_path):
    from twinrl.loop import LoopError
    from twinrl.loop.arm import make_config

    with pytest.raises(LoopError, match="no setting 'cameras'"):
        make_config({"cameras": "x"})
    with pytest.raises(LoopError, match="imitation: .*observation"):
        make_config({"imitation.observation": "depth"})
    with pytest.raises(LoopError, match="image actor"):
        make_config({"imitation.observation": "state"})
    with pytest.raises(LoopError, match="camera must be"):
        make_config({"camera": "oracle"})
    c = make_config({"imitation.fit_steps": 10, "demonstrations": 3})
    assert c.imitation["fit_steps"] == 10 and "observation" not in c.imitation  # the task's
    assert c.demonstrations == 3
    with pytest.raises(LoopError, match="grasp must be"):
        make_config({"grasp": "yes"})
    for bad in (4, 64.5, True, "128"):
        with pytest.raises(LoopError, match="image_size must be an integer >= 16 or null"):
            make_config({"image_size": bad})


def test_the_grasp_is_identified_by_default_where_it_was_measured_to_help():
    # needle and peg: the fit lands 0.7-3.4 mm from the hidden grasp (nominal: 2-12 mm); the
    # spatula's 2.1-2.4 mm (nominal 4.6-13 mm), and its loops with it and the calibrated
    # controller planned 45/48 on twins 1 and 2
    from twinrl.loop.arm import grasp_on, make_config

    c = make_config()
    assert all(grasp_on(c, t) for t in ("needle_threading", "peg_insertion", "spatula_flipping"))
    assert not grasp_on(make_config({"grasp": False}), "spatula_flipping")
    assert grasp_on(make_config({"grasp": True}), "needle_threading")
    assert not grasp_on(make_config({"grasp": False}), "needle_threading")


def test_qs_choice_is_deployed_only_where_q_ranks_its_held_out_states(tmp_path):
    from twinrl.loop import LoopError
    from twinrl.loop.arm import deployed_camera, make_config

    def camera(rank, **settings):  # the sensing stage's rank correlation, as it gives it
        return deployed_camera(make_config(settings), rank)

    assert camera(0.38) == "selected" and camera(0.35) == "selected"
    assert camera(0.31) == "default"  # the peg's Q there cost 6 points on 50 real starts
    assert camera(-0.12) == "default" and camera(None) == "default"
    assert camera(float("nan")) == "default"
    assert camera(-0.12, camera_min_rank=-1.0) == "selected"
    assert camera(0.9, camera="random") == "random"
    with pytest.raises(LoopError, match="camera_min_rank must be in"):
        make_config({"camera_min_rank": 2})


def test_the_spatula_stage_runs_dagger_unless_told_otherwise():
    # the spatula's target-cloud actor needs four DAgger rounds on solved labels (README); the
    # other tasks clone alone; a --set imitation.FIELD wins over the task's setting
    from twinrl import envs
    from twinrl.loop.arm import imitation_settings, make_config

    spatula, needle = envs.make("spatula_flipping"), envs.make("needle_threading")
    s = imitation_settings(make_config(), spatula)
    assert (s["dagger_rounds"], s["solved_labels"], s["observation"]) == (4, True, "target")
    s = imitation_settings(make_config(), needle)
    assert (s["dagger_rounds"], s["observation"], "solved_labels" in s) == (0, "pose", False)
    s = imitation_settings(make_config({"imitation.dagger_rounds": 1}), spatula)
    assert s["dagger_rounds"] == 1 and s["solved_labels"] and s["views"] == 8
    # three clonings on every task unless told otherwise
    assert s["restarts"] == 3 and imitation_settings(make_config(), needle)["restarts"] == 3
    assert imitation_settings(make_config({"imitation.restarts": 1}), needle)["restarts"] == 1


def test_resuming_a_run_recorded_with_other_images_is_one_line(tmp_path):
    """A run whose dataset holds images of another size (one an older twinrl started: the
    needle's went from 64x64 to 128x128) is refused on --resume in one line naming the sizes,
    before any stage runs; the recorded episodes stay as they were."""
    from twinrl import envs
    from twinrl.loop import LoopError
    from twinrl.loop import arm as loop_arm
    from twinrl.real.dataset import DatasetWriter

    out = tmp_path / "run"
    env = envs.make("peg_insertion")
    with DatasetWriter(out / "dataset", env="peg_insertion", obs_shape=(env.observation_size,),
                       action_shape=(env.action_size,), obs_dtype=np.float32,
                       action_dtype=np.float32,
                       image_shapes={"rgb": (32, 32, 3), "depth": (32, 32),
                                     "segmentation": (32, 32)}):
        pass
    before = sorted(p.name for p in (out / "dataset").iterdir())
    with pytest.raises(LoopError, match="records 64x64 images") as e:
        loop_arm.run("peg_insertion", out, seed=0, resume=True, progress=False)
    assert "\n" not in str(e.value) and "[32, 32]" in str(e.value)
    # the loop's own image size (--set image_size=N) is what it records at
    (out / "loop.json").unlink()
    with pytest.raises(LoopError, match="records 48x48 images"):
        loop_arm.run("peg_insertion", out, loop_arm.make_config({"image_size": 48}), seed=0,
                     resume=True, progress=False)
    assert sorted(p.name for p in (out / "dataset").iterdir()) == before


def test_a_runs_env_is_rebuilt_at_the_image_size_it_ran_with(tmp_path):
    """``twinrl.loop.arm.run_env`` (what the benches rebuild a run's twin with): the run's
    ``image_size`` setting, else the task's -- also for a run written before the setting."""
    import json

    from twinrl.loop import arm as loop_arm
    from twinrl.report import to_jsonable

    config = loop_arm.make_config({"image_size": 96})
    (tmp_path / "loop.json").write_text(json.dumps(
        {"env": "needle_threading", "seed": 0, "config": to_jsonable(config)}))
    assert loop_arm.run_env(tmp_path).config.image_size == 96
    assert loop_arm.run_env(tmp_path, pose_hinge_grid=2).config.pose_hinge_grid == 2
    old = {"env": "needle_threading", "seed": 0, "config": {"rounds": 1}}
    (tmp_path / "loop.json").write_text(json.dumps(old))
    assert loop_arm.run_env(tmp_path).config.image_size == 64


def test_a_run_started_before_a_setting_existed_resumes_at_its_default(tmp_path):
    """``loop.json`` without a setting a later twinrl added (here ``image_size``) resumes when
    the setting is at its default; a setting it names with another value is still refused."""
    from twinrl.loop import LoopError, check_settings
    from twinrl.loop.arm import make_config
    from twinrl.report import to_jsonable

    out = tmp_path / "run"
    config = make_config({})
    check_settings("needle_threading", out, config, 0, resume=False)
    saved = json.loads((out / "loop.json").read_text())
    del saved["config"]["image_size"]
    (out / "loop.json").write_text(json.dumps(saved))
    assert check_settings("needle_threading", out, config, 0, resume=True) == out
    assert json.loads((out / "loop.json").read_text())["config"] == to_jsonable(config)
    with pytest.raises(LoopError, match="other settings"):
        check_settings("needle_threading", out, make_config({"image_size": 128}), 0,
                       resume=True)
    saved["config"]["rounds"] = 3
    saved["config"]["imitation"] = {**saved["config"]["imitation"], "views": 4}
    (out / "loop.json").write_text(json.dumps(saved))
    # the error names the --set arguments that resume it as it ran (a default that changed)
    with pytest.raises(LoopError, match=r"other settings \(pass --set imitation.views=4 --set "
                                        r"rounds=3\)"):
        check_settings("needle_threading", out, config, 0, resume=True)
    fixed = make_config({"rounds": 3, "imitation.views": 4})
    assert check_settings("needle_threading", out, fixed, 0, resume=True) == out
    with pytest.raises(LoopError, match="seed 0, not 1"):
        check_settings("needle_threading", out, fixed, 1, resume=True)


def test_qs_choice_is_deployed_only_where_it_beats_the_default_in_the_identified_twin(
        tmp_path, monkeypatch):
    """The ``camera_check`` stage: below the rank gate no check is played; above it Q's choice
    is deployed only if it succeeds on more of the fresh starts in the identified twin than the
    default camera (a tie keeps the default); ``camera_check=0`` is the rank gate alone. The
    decision and its figures land in ``camera_check.json`` (what a resumed run reads back) and
    the round's record."""
    from types import SimpleNamespace

    from twinrl.learn.camera_choice import CameraCheck
    from twinrl.loop import LoopError, arm_stages
    from twinrl.loop.arm import make_config
    from twinrl.loop.engine import Progress
    from twinrl.loop.rundir import RoundDir

    outcome, calls = {}, []

    def fake_check(run, r, rdir, env):  # the identified twin's episodes, as check_choice gives
        calls.append(r)
        n = run.config.camera_check
        sel, dft = (np.array([1.0] * k + [0.0] * (n - k)) for k in outcome["counts"])
        return CameraCheck(sel, dft, sel, dft, np.zeros((n, 3)))
    monkeypatch.setattr(arm_stages, "sim_camera_check", fake_check)

    def decide(rank, counts=(0, 0), **settings):
        outcome["counts"] = counts
        d = tmp_path / f"run{len(list(tmp_path.iterdir()))}"
        rdir = RoundDir(d / "round1")
        rdir.make()
        said = []
        run = SimpleNamespace(config=make_config(settings), seed=0, say=said.append,
                              prog=Progress(d / "progress.json"))
        cam = arm_stages.check_camera(run, 1, rdir, None, rank)["deploy_camera"]
        assert arm_stages.load_deploy_camera(run, rdir) == {"deploy_camera": cam}
        return cam, json.loads(rdir.camera_check.read_text()), run.prog.record(1), said

    cam, doc, rec, said = decide(0.2, (5, 1))
    assert cam == "default" and doc["reason"] == "rank" and not calls  # no check played
    assert "below camera_min_rank" in said[0] and rec["sim_selected_success"] is None
    cam, doc, rec, said = decide(0.5, (15, 12))
    assert cam == "selected" and calls == [1] and doc["selected_success"] == 0.75
    assert rec["sim_default_success"] == 0.6 and rec["deploy_camera"] == "selected"
    assert "15/20" in said[-1] and "12/20" in said[-1]
    cam, doc, rec, said = decide(0.5, (12, 12))
    assert cam == "default" and doc["reason"] == "identified twin"
    assert "does not pay" in said[-1]
    cam, doc, *_ = decide(0.5, (2, 3), camera_check=0)
    assert cam == "selected" and len(calls) == 2  # the rank gate alone: no check
    with pytest.raises(LoopError, match="camera_check must be an integer"):
        make_config({"camera_check": -1})
