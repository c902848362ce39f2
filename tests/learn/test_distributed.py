"""Training on two processes (``twinrl.learn.distributed``): JAX's multi-process runtime on
127.0.0.1, Gloo's CPU collectives, one CPU device per process.

Each run is a subprocess of ``tests/learn/_dist_worker.py`` (a tiny SHAC through the runner, a
tiny HDS, the imitation actor's minibatch fit and the sensing Q's image fit). Two processes hold
one global batch between them, so they must end where one process ends: the random draws are the
same (every key comes from the one global key, and JAX's partitionable threefry gives each
device its slice of the same numbers), and only the order of the all-reduced sums differs (a sum
over 2 devices' halves is not bit-equal to one device's sum in float32). Measured: SHAC's
parameters after 4 epochs within 4e-9, the fit's after 60 Adam steps within 1.2e-7, HDS's after
3 epochs within 6e-8, the Q's after 12 steps within 2e-7 (parameters of order 0.05-1.5); the
tests allow 1e-5, far below any change of the algorithm (a step of Adam moves a parameter by
~1e-2). HDS's annealing compares two energies that differ between the runs by ~3e-8: a proposal
whose energy tied the current one's that closely could be taken on one process count and not on
the other (none does here).
"""

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from twinrl.learn import distributed
from twinrl.learn.checkpoint import load_policy

ROOT = Path(__file__).resolve().parents[2]
TIMEOUT = 20
"""Seconds a worker waits for its peer to join, and without a heartbeat before it is dead."""


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _worker(out, *args, n=1, pid=0, port=None, timeout=TIMEOUT):
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [sys.executable, "-m", "tests.learn._dist_worker", "--out", str(out), *args,
           "--timeout", str(timeout)]
    if n > 1:
        cmd += ["--coordinator", f"127.0.0.1:{port}", "--num-processes", str(n),
                "--process-id", str(pid)]
    return subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _pair(out, *args):
    port = _port()
    return [_worker(out, *args, n=2, pid=i, port=port) for i in range(2)]


def _finish(procs, timeout=240):
    """Wait for every worker, assert they succeeded; their stderr."""
    outs = [p.communicate(timeout=timeout) for p in procs]
    for p, (o, e) in zip(procs, outs):
        assert p.returncode == 0, f"worker failed ({p.returncode}):\n{o}\n{e[-3000:]}"
    return [e for _, e in outs]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same training on one process and on two, side by side, and the stderr of the second
    process of two."""
    one, two = tmp_path_factory.mktemp("one"), tmp_path_factory.mktemp("two")
    what = ("--what", "fit", "q", "hds", "ppo", "shac")
    procs = [_worker(one, *what), *_pair(two, *what)]
    errs = _finish(procs)
    return one, two, errs[2]


def test_two_processes_train_shac_as_one_does(runs):
    one, two, _ = runs
    (_, a, meta_a), (_, b, meta_b) = load_policy(one / "policy"), load_policy(two / "policy")
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-5)
    assert meta_b["metrics"]["epoch"] == 4 == meta_a["metrics"]["epoch"]
    # process 0 alone wrote the run; its metrics are the one-process run's
    rows = (two / "metrics.csv").read_text().splitlines()
    assert len(rows) == 5 and rows[0] == (one / "metrics.csv").read_text().splitlines()[0]
    assert json.loads((two / "summary.json").read_text())["epochs"] == 4


def test_two_processes_fit_the_imitation_actor_as_one_does(runs):
    one, two, _ = runs
    a, b = np.load(one / "fit.npz"), np.load(two / "fit.npz")
    assert set(a) == set(b)
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=0, atol=1e-5, err_msg=k)
    assert a["losses"][-1] < 0.5 * a["losses"][0]  # it fitted something


def test_two_processes_fit_the_sensing_q_as_one_does(runs):
    """The sensing Q's fit: image minibatches, each augmented (RGB jitter, random shift), split
    over the two processes, an ensemble of two members."""
    one, two, _ = runs
    a, b = np.load(one / "q.npz"), np.load(two / "q.npz")
    assert set(a) == set(b) and len(a) > 4
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=0, atol=1e-5, err_msg=k)
    assert a["losses"][-1] < 0.5 * a["losses"][0]  # it fitted something


def test_two_processes_run_a_brax_ppo_iteration_in_step(runs):
    """Brax PPO through its own multi-process path: each process steps half the environments
    with its own random stream (Brax folds the process index into its keys, so the run is not
    one process's), and the gradients are averaged over both, so the two processes end with
    the same parameters; ``twinrl train --algo ppo``'s runner writes the run from process 0."""
    one, two, _ = runs
    a, b, alone = (np.load(two / "ppo0.npz"), np.load(two / "ppo1.npz"),
                   np.load(one / "ppo0.npz"))
    leaves = [k for k in a if k != "env_steps"]
    assert len(leaves) > 2
    for k in leaves:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
        assert np.all(np.isfinite(a[k])), k
    assert any(not np.allclose(a[k], alone[k]) for k in leaves)  # not one process's streams
    assert list(a["env_steps"]) == [0, 128] == list(alone["env_steps"])
    assert b["env_steps"].size == 0  # Brax reports on process 0 alone
    rows = (two / "ppo" / "metrics.csv").read_text().splitlines()
    assert len(rows) == 3 and [r.split(",")[1] for r in rows[1:]] == ["0.0", "128.0"]
    _, params, meta = load_policy(two / "ppo" / "policy")
    assert meta["algo"] == "ppo" and meta["metrics"]["env_steps"] == 128
    saved = jax.tree_util.tree_leaves(params)
    assert [x.shape for x in saved] == [a[k].shape for k in leaves]


def test_the_process_that_does_not_write_says_nothing(runs):
    """Process 1 opens the training state read only (process 0 writes it): orbax's notices
    about that are expected and not shown; nothing else is printed but Gloo's connection line."""
    *_, err = runs
    assert "read only" not in err and "WARNING" not in err, err[-2000:]
    assert all(line.startswith("[Gloo]") for line in err.splitlines()), err[-2000:]


def test_two_processes_train_hds_as_one_does(runs):
    """Exploration noise, the annealed step size, rollouts through a model and the critic, split
    over two processes: the same parameters, and the same annealing decisions (each process
    reads every process's windows before it compares the halves' energies)."""
    one, two, _ = runs
    a, b = np.load(one / "hds.npz"), np.load(two / "hds.npz")
    assert set(a) == set(b)
    for k in a:
        np.testing.assert_allclose(a[k], b[k], rtol=1e-6, atol=1e-5, err_msg=k)
    for k in ("step_size", "step_size_proposal", "sa_accept"):  # discrete: exactly the same
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    assert 0 < a["sa_accept"].sum() < 3 and np.ptp(a["step_size"]) > 0  # the chain moved


def _steps(directory: Path) -> list[int]:
    return sorted(int(p.name) for p in directory.glob("[0-9]*") if p.name.isdigit())


@pytest.mark.parametrize("killed", [1, 0], ids=["peer", "coordinator"])
def test_a_dead_process_ends_the_other_loudly_and_one_process_resumes(tmp_path, killed):
    epochs = "40"
    procs = _pair(tmp_path, "--what", "shac", "--epochs", epochs)
    deadline = time.monotonic() + 240
    while len(_steps(tmp_path / "train_state")) < 1 or _steps(tmp_path / "train_state")[-1] < 2:
        assert all(p.poll() is None for p in procs), "a worker ended before the kill"
        assert time.monotonic() < deadline, "no checkpoint within 240 s"
        time.sleep(0.1)
    procs[killed].send_signal(signal.SIGKILL)
    t0 = time.monotonic()
    survivor = procs[1 - killed]
    _, err = survivor.communicate(timeout=TIMEOUT + 30)
    waited = time.monotonic() - t0
    procs[killed].communicate()
    assert survivor.returncode != 0
    assert waited < TIMEOUT + 10, f"the survivor took {waited:.1f} s to stop"
    assert "Traceback" not in err and "Check failure" not in err, err[-2000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith(("worker: error:", "twinrl: error:")), err[-2000:]
    print(f"process {1 - killed} stopped {waited:.2f} s after process {killed} was killed "
          f"(exit {survivor.returncode}): {last}")

    # one process continues the run from the last checkpoint the writer completed
    saved = _steps(tmp_path / "train_state")[-1]
    alone = _worker(tmp_path, "--what", "shac", "--epochs", epochs, "--resume")
    _finish([alone])
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["resumed"] and summary["epochs"] == 40
    assert saved >= 2
    rows = (tmp_path / "metrics.csv").read_text().splitlines()[1:]
    assert [int(float(r.split(",")[0])) for r in rows] == list(range(1, 41))


def test_an_error_in_one_process_stops_both_at_once(tmp_path):
    procs = _pair(tmp_path, "--what", "fit", "--fail")
    t0 = time.monotonic()
    (_, err0), (_, err1) = (p.communicate(timeout=TIMEOUT + 120) for p in procs)
    assert procs[0].returncode != 0 and procs[1].returncode != 0
    assert time.monotonic() - t0 < TIMEOUT + 100
    # the failing process shows its traceback and says why it stopped; its peer, in one line
    assert "ValueError: injected failure in process 1" in err1
    assert err1.strip().splitlines()[-1].startswith("worker: error: process 1 of 2 stopped:")
    assert "Traceback" not in err0 and "Check failure" not in err0, err0[-2000:]
    assert err0.strip().splitlines()[-1].startswith(("worker: error:", "twinrl: error:"))


def test_a_coordinator_nobody_answers_fails_in_one_line(tmp_path):
    t0 = time.monotonic()
    p = _worker(tmp_path, "--what", "fit", n=2, pid=1, port=_port(), timeout=3)
    _, err = p.communicate(timeout=60)
    waited = time.monotonic() - t0
    assert p.returncode != 0 and waited < 3 + 30
    assert "Check failure" not in err, err[-2000:]
    last = err.strip().splitlines()[-1]
    assert last.startswith(("worker: error:", "twinrl: error:")), err[-2000:]
    print(f"gave up after {waited:.1f} s (timeout 3 s, exit {p.returncode}): {last}")


def test_brax_apg_on_two_processes_is_refused_in_one_line(tmp_path):
    procs = _pair(tmp_path, "--what", "apg")
    for p in procs:
        _, err = p.communicate(timeout=TIMEOUT + 120)
        assert p.returncode == 1, err[-2000:]
        assert "Traceback" not in err, err[-2000:]
        assert "Brax APG cannot run on several processes" in err.strip().splitlines()[-1]


def test_one_process_is_left_alone():
    assert distributed.initialize() == 1 and not distributed.is_distributed()
    assert distributed.is_writer()
    assert distributed.process_rows(8) == slice(0, 8)
    x = np.arange(12.0).reshape(6, 2)
    np.testing.assert_array_equal(distributed.to_host(distributed.global_batch({"x": x}))["x"], x)


def test_the_environment_asks_for_several_processes_only_when_it_says_so():
    assert not distributed.requested({})
    assert not distributed.requested({"SLURM_JOB_ID": "1", "SLURM_STEP_NODELIST": "n1",
                                      "SLURM_NTASKS": "1"})
    assert distributed.requested({"SLURM_JOB_ID": "1", "SLURM_STEP_NODELIST": "n[1-2]",
                                  "SLURM_NTASKS": "2"})
    assert distributed.requested({"OMPI_MCA_orte_hnp_uri": "x", "OMPI_COMM_WORLD_SIZE": "4"})
    assert distributed.requested({"JAX_COORDINATOR_ADDRESS": "10.0.0.1:1234"})


def test_bad_settings_are_named():
    with pytest.raises(distributed.DistributedError, match="HOST:PORT"):
        distributed.initialize("nohost", 2, 0)
    with pytest.raises(distributed.DistributedError, match=r"process_id 2 is not in \[0, 2\)"):
        distributed.initialize("127.0.0.1:1234", 2, 2)


def test_the_train_command_checks_its_distributed_flags(capsys):
    from twinrl.cli import main

    assert main(["train", "--env", "pendulum_swingup", "--algo", "shac",
                 "--coordinator", "127.0.0.1:1234"]) == 2
    assert "go together" in capsys.readouterr().err
    assert main(["train", "--env", "pendulum_swingup", "--algo", "shac", "--coordinator",
                 "10.0.0.1", "--num-processes", "2", "--process-id", "0"]) == 1
    assert "HOST:PORT" in capsys.readouterr().err
