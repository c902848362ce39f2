"""``twinrl.loop`` on two processes (``jax.distributed`` on 127.0.0.1): process 0 runs the loop
and the real twin and writes every file; process 1 follows it through ``progress.json`` and
runs the learning stages (learn, compare) with it, their collectives spanning both processes;
both resume the finished run.

The stages that compile are stand-ins, as in ``tests/test_loop.py`` (a sysid that returns the
nominal parameters; a trainer that compiles nothing), and the stand-in trainer gathers every
process's index through the runtime, so each process notes which processes learned together.
"""

import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = textwrap.dedent("""
    import dataclasses, sys
    from pathlib import Path
    from twinrl.learn import distributed

    out, port, pid = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
    resume = sys.argv[4] == "resume"
    distributed.initialize(f"127.0.0.1:{port}", 2, pid, timeout_s=60, heartbeat_s=60)
    import jax
    import numpy as np
    from twinrl import eval as evaluation, loop
    from twinrl.envs import System
    from twinrl.learn import runner
    from twinrl.learn.common import MetricLog
    from twinrl.learn.networks import make_policy
    from twinrl.real2sim import sysid

    log = out.parent / f"calls{pid}.log"

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

    @dataclasses.dataclass(frozen=True)
    class Config:
        epochs: int = 2

    def train(env, config, rng, *, progress_fn=None, checkpoint_fn=None, restore=None):
        # every process's index, gathered through the runtime: who learned together
        both = distributed.to_host(distributed.global_batch(
            np.full((1,), jax.process_index(), np.float32)))
        note(f"train {both.astype(int).tolist()}")
        pol = make_policy(env.observation_size, env.action_size, (8,))
        state, log = {"params": pol.init(rng)}, MetricLog()
        for e in range(config.epochs):
            log.record(epoch=e, env_steps=10 * (e + 1), grad_norm=0.0, **{"return": 0.5 * e})
            if checkpoint_fn:
                checkpoint_fn(e, state, log.as_dict())
        return pol, state["params"], log.as_dict()

    sysid.fit = fit
    evaluation.param_errors = lambda *a: {"cart_mass": 0.0}
    runner.ALGORITHMS["toy"] = runner.Algorithm("__main__", "train", "Config", {}, True)
    config = loop.LoopConfig(rounds=1, episodes_per_round=1, algo="toy", compare="toy", epochs=2,
                             model_fraction=0.0, hybrid=False, residual=False, oracle=False,
                             video=False, eval_episodes=1)
    with distributed.guard("child"):
        summary = loop.run("cartpole_swingup", out, config, seed=4, progress=False,
                           resume=resume)
    note(f"finished {sorted(summary)}")
""")


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _pair(out: Path, mode: str) -> list[str]:
    """Both processes of the loop into ``out``; their output, once both succeeded."""
    port = _port()
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    procs = [subprocess.Popen([sys.executable, "-c", CHILD, str(out), str(port), str(i), mode],
                              cwd=ROOT, env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for i in range(2)]
    texts = [p.communicate(timeout=300)[0] for p in procs]
    for p, text in zip(procs, texts):
        assert p.returncode == 0, text[-3000:]
    return texts


def test_process_0_runs_the_loop_and_both_learn_and_resume(tmp_path):
    out = tmp_path / "run"
    texts = _pair(out, "fresh")
    calls = [(tmp_path / f"calls{i}.log").read_text().splitlines() for i in range(2)]
    # process 0 identified the simulator and deployed; process 1 only learned, with it, twice
    # (the deployed learner and the compared one), and returned no summary of its own
    assert calls[0][0] == "sysid 250" and not any(c.startswith("sysid") for c in calls[1])
    for c in calls:
        assert c.count("train [0, 1]") == 2 and len([x for x in c if "train" in x]) == 2, c
    assert calls[1][-1] == "finished []" and "rounds" in calls[0][-1]
    summary = json.loads((out / "summary.json").read_text())
    assert [r["round"] for r in summary["rounds"]] == [0, 1]
    assert summary["rounds"][1]["real_steps"] == 500
    done = json.loads((out / "progress.json").read_text())["done"]
    assert {"round1/learn", "round1/compare", "round1/deploy"} <= set(done)
    assert "Traceback" not in texts[1] and "WARNING" not in texts[1], texts[1][-2000:]

    # both resume the finished run: every stage read back, nothing learned or identified again
    _pair(out, "resume")
    again = [(tmp_path / f"calls{i}.log").read_text().splitlines()[len(c):]
             for i, c in enumerate(calls)]
    assert again[1] == ["finished []"] and len(again[0]) == 1, again
    assert json.loads((out / "summary.json").read_text())["rounds"] == summary["rounds"]
