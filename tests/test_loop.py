"""``twinrl.loop``: a run killed with SIGKILL in the middle of a round's real deployment and
resumed keeps every real transition it had recorded, does not redo finished stages, and finishes
with the same bookkeeping as a run that was never interrupted.

The stages that compile (sysid, the learner) are replaced in the child process by cheap stand-ins
(a sysid that returns the nominal parameters, a trainer that returns a seeded random policy): this tests the loop's
resume bookkeeping, the real-twin recording and the dataset's durability, each stage having its own
tests. The deployed policy sleeps a few milliseconds a step so the kill lands inside an episode.
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

ROUNDS, K, T = 2, 2, 250

CHILD = textwrap.dedent("""
    import dataclasses, sys, time
    from pathlib import Path
    from twinrl import eval as evaluation, loop
    from twinrl.loop import cartpole
    from twinrl.learn import runner
    from twinrl.learn.common import MetricLog
    from twinrl.learn.networks import make_policy
    from twinrl.envs import System
    from twinrl.real2sim import sysid

    out, resume = Path(sys.argv[1]), sys.argv[2] == "resume"
    log = out.parent / "calls.log"

    def note(s):
        with open(log, "a") as f:
            f.write(s + "\\n")

    class Result:  # the fields of a SysidResult the loop stores
        def __init__(self, env):
            self.params, self.latency, self.table = env.sim.default_params(), 0, []
            self.loss, self.sim_rollouts, self.seconds = 0.0, 0, 0.0
            self.system = System(params=self.params, latency=0, task=env.name)

    def fit(env, data, config=None, **kw):
        note(f"sysid {len(data)}")
        return Result(env)

    real_deployed = cartpole.deployed_policy

    def slow_deployed(*a, **k):
        act = real_deployed(*a, **k)
        def slow(o):
            time.sleep(0.004)
            return act(o)
        return slow

    @dataclasses.dataclass(frozen=True)
    class Config:
        epochs: int = 2

    def train(env, config, rng, *, progress_fn=None, checkpoint_fn=None, restore=None):
        # a trainer that follows the contract and compiles nothing: a seeded random policy
        note("train")
        pol = make_policy(env.observation_size, env.action_size, (8,))
        state, log = {"params": pol.init(rng)}, MetricLog()
        if restore is not None:
            state, hist = restore(state)
            log = MetricLog(hist)
        for e in range(len(log.history.get("epoch", [])), config.epochs):
            row = log.record(epoch=e, env_steps=10 * (e + 1), grad_norm=0.0, **{"return": 0.5 * e})
            if checkpoint_fn:
                checkpoint_fn(e, state, log.as_dict())
        return pol, state["params"], log.as_dict()

    sysid.fit = fit
    evaluation.param_errors = lambda *a: {"cart_mass": 0.0}
    cartpole.deployed_policy = slow_deployed
    runner.ALGORITHMS["toy"] = runner.Algorithm("__main__", "train", "Config", {}, True)
    config = loop.LoopConfig(rounds=%d, episodes_per_round=%d, algo="toy", compare="toy",
                             epochs=2,
                             model_fraction=0.0, hybrid=False, residual=False, oracle=False,
                             video=False, eval_episodes=1)
    note("start resume" if resume else "start")
    loop.run("cartpole_swingup", out, config, seed=4, resume=resume, progress=False)
    note("finished")
""" % (ROUNDS, K))


def _child(out: Path, mode: str):
    return subprocess.Popen([sys.executable, "-c", CHILD, str(out), mode],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _done(out: Path) -> list[str]:
    try:
        return json.loads((out / "progress.json").read_text())["done"]
    except (FileNotFoundError, json.JSONDecodeError):
        return []


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    base = tmp_path_factory.mktemp("loop")
    full, killed = base / "full" / "run", base / "killed" / "run"
    for d in (full, killed):
        d.parent.mkdir()
    p = _child(full, "fresh")
    text, _ = p.communicate(timeout=600)
    assert p.returncode == 0, text

    # the same real twin for both runs: its hidden perturbation's secret salt copied over (the
    # default salt is seeded, but a TWINRL_TWIN_SALT=random run draws its own)
    (killed / "eval").mkdir(parents=True)
    (killed / "eval" / "twin.json").write_bytes((full / "eval" / "twin.json").read_bytes())
    p = _child(killed, "fresh")
    deadline = time.time() + 600
    # wait for round 1's first deployed episode to be recorded: the second is then under way
    while time.time() < deadline and "round1/deploy_partial" not in _done(killed):
        assert p.poll() is None, p.communicate()[0]
        time.sleep(0.02)
    time.sleep(0.4)
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    done_at_kill = _done(killed)
    at_kill = ds.read(killed / "dataset")
    p = _child(killed, "resume")
    text, _ = p.communicate(timeout=600)
    assert p.returncode == 0, text
    return full, killed, done_at_kill, at_kill


def test_killed_mid_episode(runs):
    _, _, done_at_kill, at_kill = runs
    assert "round1/deploy" not in done_at_kill and "round1/learn" in done_at_kill
    # round 0 and one deployed episode complete, the next one cut short
    assert int(np.sum(at_kill.episode_complete)) == 2 * K - 1
    assert (2 * K - 1) * T < len(at_kill) < 2 * K * T


def test_resume_loses_no_recorded_transition(runs):
    _, killed, _, at_kill = runs
    final = ds.read(killed / "dataset")
    n = len(at_kill)
    np.testing.assert_array_equal(final.obs[:n], at_kill.obs)
    np.testing.assert_array_equal(final.action[:n], at_kill.action)
    np.testing.assert_array_equal(final.reward[:n], at_kill.reward)
    np.testing.assert_array_equal(final.episode_id[:n], at_kill.episode_id)
    # every round's K episodes complete, plus the interrupted one kept as incomplete
    assert int(np.sum(final.episode_complete)) == K * (ROUNDS + 1)
    assert len(final.episode_complete) == K * (ROUNDS + 1) + 1
    assert len(final) == K * (ROUNDS + 1) * T + (n - (2 * K - 1) * T)


def test_finished_stages_are_not_redone(runs):
    full, killed, _, _ = runs
    calls = (killed.parent / "calls.log").read_text().split("\n")
    # sysid and training ran once per round: round 1's before the kill, round 2's after (two
    # trainings a round: the deployed learner's and the compared one's, ``compare="toy"``)
    sysids = [c for c in calls if c.startswith("sysid")]
    assert len(sysids) == ROUNDS and calls.count("train") == 2 * ROUNDS, calls
    assert calls.index("start resume") > calls.index(sysids[0])
    # the same data went into each round's sysid as in the uninterrupted run, except the
    # interrupted episode's partial transitions in round 2
    full_calls = [c for c in (full.parent / "calls.log").read_text().split("\n")
                  if c.startswith("sysid")]
    assert sysids[0] == full_calls[0]


def test_summary_matches_the_uninterrupted_run(runs):
    full, killed, _, _ = runs
    a = json.loads((full / "summary.json").read_text())
    b = json.loads((killed / "summary.json").read_text())
    assert len(a["rounds"]) == len(b["rounds"]) == ROUNDS + 1
    for ra, rb in zip(a["rounds"], b["rounds"]):
        # the same episodes from the same seeds: identical returns and sim returns
        assert ra["real_return"] == rb["real_return"], (ra, rb)
        assert ra["sim_return"] == rb["sim_return"]
    # the killed run's dataset also holds the interrupted episode's partial transitions
    assert b["rounds"][-1]["real_steps"] > a["rounds"][-1]["real_steps"]
    assert (killed / "report.md").exists() and (killed / "returns.png").exists()


def test_a_compared_learner_is_reported_beside_the_deployed_one(runs):
    full = runs[0]
    summary = json.loads((full / "summary.json").read_text())
    for rec in summary["rounds"][1:]:
        c = rec["compare"]
        assert c["algo"] == c["deployed_algo"] == "toy" and c["sim_return"] == 0.5
        # the same seeded trainer: the deployed one reaches the compared one's final return
        assert 0 <= c["deployed_s_to_compare_final"] <= c["deployed_learn_s"]
        assert (full / f"round{rec['round']}" / "compare" / "metrics.csv").exists()
    assert "## Learning wall clock against a second learner" in (full / "report.md").read_text()


def test_the_loops_inputs_hold_no_evaluation_output(runs):
    """What the stages read (the dataset, progress.json, loop.json, the rounds' artefacts) holds
    none of evaluation's outputs or the twin's secret: those are in eval/, which no stage opens;
    summary.json and report.md, written after the last stage, merge them in."""
    full, _, _, _ = runs
    ev = json.loads((full / "eval" / "evaluation.json").read_text())
    assert ev["rounds"]["round1"]["param_rel_error"] == {"cart_mass": 0.0}
    assert "sim_policy_real_return" in ev["rounds"]["round2"]
    salt = json.loads((full / "eval" / "twin.json").read_text())["salt"]
    outputs = {full / "summary.json", full / "report.md"}
    inputs = [p for p in full.rglob("*") if p.is_file() and "eval" not in p.relative_to(
        full).parts and p not in outputs and p.suffix not in (".png", ".mp4", ".gif")]
    assert any(p.name == "progress.json" for p in inputs) and any(
        p.parent.name == "dataset" for p in inputs)
    for p in inputs:
        text = p.read_bytes()
        for word in (b"param_rel_error", b"sim_policy_real_return", b"adapted_real_return",
                     b"oracle_return", b"perturbation", salt.encode()):
            assert word not in text, (p, word)
    s = json.loads((full / "summary.json").read_text())
    assert s["rounds"][1]["param_rel_error"] == {"cart_mass": 0.0}
    assert s["rounds"][2]["sim_policy_real_return"] is not None


ORACLE_PARENT = textwrap.dedent("""
    import sys, time
    from twinrl import loop
    from twinrl.loop.oracle import OracleProcess
    job = OracleProcess(sys.argv[1], 0, sys.argv[2], loop.LoopConfig(), None)
    print(job._proc.pid, flush=True)
    if sys.argv[1] == "cartpole_swingup":
        time.sleep(600)  # killed by the test while the oracle trains
    try:
        job.result()
    except loop.LoopError as e:
        print("LoopError:", str(e).strip().splitlines()[-1], flush=True)
""")


def _alive(pid: int) -> bool:
    try:  # a zombie (exited, not yet reaped) counts as gone
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(sys.platform != "linux", reason="the parent-death signal is Linux's prctl")
def test_oracle_process_reports_its_error_and_dies_with_the_loop(tmp_path):
    p = subprocess.run([sys.executable, "-c", ORACLE_PARENT, "no_such_task", str(tmp_path / "a")],
                       capture_output=True, text=True, timeout=300)
    assert "LoopError: ValueError: unknown task 'no_such_task'" in p.stdout, p.stdout + p.stderr
    p = subprocess.Popen([sys.executable, "-c", ORACLE_PARENT, "cartpole_swingup",
                          str(tmp_path / "b")], stdout=subprocess.PIPE, text=True)
    oracle_pid = int(p.stdout.readline())
    time.sleep(2.0)
    assert _alive(oracle_pid)
    os.kill(p.pid, signal.SIGKILL)
    p.wait()
    deadline = time.time() + 30
    while time.time() < deadline and _alive(oracle_pid):
        time.sleep(0.1)
    assert not _alive(oracle_pid)


def test_a_damaged_chunk_costs_its_records_not_the_run(tmp_path):
    # what `run --resume` reads at each round: the intact transitions, and one line on the damage
    from twinrl import loop

    with ds.DatasetWriter(tmp_path, env="fake", obs_shape=(2,), action_shape=(1,),
                          chunk_size=5) as w:
        for t in range(15):
            w.add(np.full(2, t), [0.0], 1.0, np.full(2, t + 1), False, t == 14)
    chunk = tmp_path / "chunk-00000-00001.twr"
    data = bytearray(chunk.read_bytes())
    data[-60] ^= 0xFF  # inside the body of the chunk's last step record
    chunk.write_bytes(bytes(data))
    said = []
    got = loop.read_dataset(tmp_path, lambda *a, **k: said.append(" ".join(map(str, a))))
    assert len(got) == 14 and got.step.tolist() == [*range(9), *range(10, 15)]
    assert len(said) == 1 and "\n" not in said[0]
    assert "14 intact transitions" in said[0] and "chunk-00000-00001.twr" in said[0]
    assert loop.episodes_in(tmp_path) == 0  # the episode has a gap: incomplete, re-recorded


def test_resume_without_the_twins_secret_is_refused(tmp_path):
    # a run recorded by a twin whose secret is gone (or by a version of twinrl before it): a
    # new salt would be another twin mid-run, so --resume stops with one line
    from twinrl import loop

    out = tmp_path / "run"
    (out / "dataset").mkdir(parents=True)
    config = loop.LoopConfig(oracle=False, video=False)
    from twinrl import report

    report.write_json(out / "loop.json", {"env": "pendulum_swingup", "seed": 0,
                                          "config": report.to_jsonable(config)})
    with pytest.raises(loop.LoopError, match="no eval/twin.json"):
        loop.run("pendulum_swingup", out, config, resume=True, progress=False)


def test_a_sysid_json_written_before_the_system_still_resumes(tmp_path):
    # runs made before the System wrote `params` and `latency` side by side: the System is
    # rebuilt from them (what the later stages simulate), and a file with neither is refused
    from twinrl import envs, loop
    from twinrl.envs.wrappers import LatencyWrapper
    from twinrl.loop.rundir import RoundDir

    params = envs.make("pendulum_swingup").sim.default_params().scaled(mass=1.3)
    old = {k: np.asarray(v, np.float64).tolist() for k, v in params.as_dict().items()}
    from twinrl import report

    report.write_json(tmp_path / "sysid.json", {"latency": 2, "params": old, "table": [],
                                                "loss": 0.1, "sim_rollouts": 3, "seconds": 1.0})
    system = RoundDir(tmp_path).identified_system("pendulum_swingup")
    assert system.latency == 2 and system.task == "pendulum_swingup"
    for k, v in params.as_dict().items():
        np.testing.assert_array_equal(np.asarray(getattr(system.params, k)),
                                      np.asarray(v, np.float64))
    env = envs.make("pendulum_swingup", system=system)
    assert isinstance(env, LatencyWrapper) and env.sys is system
    report.write_json(tmp_path / "sysid.json", {"table": []})
    with pytest.raises(loop.LoopError, match="neither a 'system' nor the older"):
        RoundDir(tmp_path).identified_system("pendulum_swingup")


def test_a_stage_hands_on_what_it_made_and_a_resumed_run_what_it_saved(tmp_path):
    # the engine passes a stage's returned values on; a stage marked done is not run again, its
    # values are read back from its own files (progress.json only says it is done)
    import json
    from types import SimpleNamespace

    from twinrl.loop import LoopError, Progress, RunDir, Stage

    made = []

    def make(run, r, rdir, x):
        made.append(x)
        (rdir.path / "y.json").write_text(json.dumps(x + 1))
        run.prog.mark(f"round{r}/s")
        return {"y": x + 1}

    def load(run, rdir, **_):
        return {"y": json.loads((rdir.path / "y.json").read_text())}

    stage = Stage("s", needs=("x",), gives=("y",), make=make, load=load)
    run = SimpleNamespace(config=None, dir=RunDir(tmp_path),
                          prog=Progress(tmp_path / "progress.json"))
    assert stage(run, 1, {"x": 1}) == {"y": 2} and made == [1]
    run.prog = Progress(tmp_path / "progress.json")  # a resumed run
    assert stage(run, 1, {"x": 5}) == {"y": 2} and made == [1]
    assert "y" not in json.loads((tmp_path / "progress.json").read_text())["rounds"].get(
        "round1", {})
    off = Stage("t", needs=(), gives=("z",), make=make, enabled=lambda c: False)
    assert off(run, 1, {}) == {"z": None}
    wrong = Stage("u", needs=(), gives=("z",), make=lambda run, r, rdir: {"w": 0})
    with pytest.raises(LoopError, match="declares"):
        wrong(run, 1, {})


def test_a_deployment_killed_by_an_older_twinrl_resumes_from_its_rows(tmp_path):
    # the deployed episodes' rows live in round<r>/deploy_partial.json; a run an older twinrl
    # killed kept them in progress.json, where they are read when the file is missing
    import json
    from types import SimpleNamespace

    from twinrl.loop import Progress, RunDir
    from twinrl.loop.shared import EpisodeLog

    prog = Progress(tmp_path / "progress.json")
    prog.mark("round1/deploy_partial", deploy_returns_partial=[1.5])
    run = SimpleNamespace(dir=RunDir(tmp_path), prog=prog)
    log = EpisodeLog(run, 1, "deploy_returns_partial")
    assert log.rows == [1.5]
    (tmp_path / "round1").mkdir()
    log.add(2.5)
    assert json.loads((tmp_path / "round1" / "deploy_partial.json").read_text()) == {
        "episodes": [1.5, 2.5]}
    assert Progress(tmp_path / "progress.json").record(1)["deploy_episodes"] == 2
    assert EpisodeLog(run, 1, "deploy_returns_partial").rows == [1.5, 2.5]
