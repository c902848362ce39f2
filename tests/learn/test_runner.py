"""The run directory of ``twinrl train``/``eval``: files, policy checkpoint round trip, resume,
metrics CSV/TensorBoard, and clear errors (runner plumbing, with a toy trainer)."""

import csv
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl.learn import checkpoint, runner
from twinrl.learn.networks import NetworkConfig, make_network, make_policy
from twinrl.report import MetricsWriter

ENV = "pendulum_swingup"


@pytest.fixture(scope="module", autouse=True)
def toy_algorithm():
    runner.ALGORITHMS["toy"] = runner.Algorithm("tests.learn._toy", "train", "ToyConfig", {}, True)
    yield
    runner.ALGORITHMS.pop("toy")


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("full")
    return out, runner.train_run(ENV, "toy", out, epochs=4, seed=3, progress=False)


def test_run_directory_has_every_output(full_run):
    out, summary = full_run
    for name in ("run.json", "metrics.csv", "curve.png", "summary.json", "policy/checkpoint.json"):
        assert (out / name).exists(), name
    assert list((out / "tb").glob("events.out.tfevents.*"))
    rows = (out / "metrics.csv").read_text().splitlines()
    assert rows[0].split(",")[:2] == ["epoch", "env_steps"] and len(rows) == 5
    assert summary["epochs"] == 4 and summary["final"]["epoch"] == 3


def test_final_figures_are_the_kept_epochs(tmp_path):
    # a trainer that returns an earlier epoch's policy (imitation's best round) marks it ``kept``:
    # the summary's final row and the checkpoint's metrics are that epoch's, not the last one's
    s = runner.train_run(ENV, "toy", tmp_path, epochs=3, seed=3, progress=False,
                         overrides={"kept": 1})
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [float(r["kept"]) for r in rows] == [0.0, 1.0, 0.0]
    assert s["final"]["epoch"] == 1 and s["final"]["return"] == float(rows[1]["return"])
    _, _, meta = checkpoint.load_policy(tmp_path)
    assert meta["metrics"]["epoch"] == 1 and meta["metrics"]["kept"] == 1.0


def test_policy_checkpoint_loads_without_the_trainer(full_run):
    out, _ = full_run
    net, params, meta = checkpoint.load_policy(out)        # the run dir resolves to policy/
    assert meta["algo"] == "toy" and meta["env"] == ENV and meta["seed"] == 3
    obs = jnp.linspace(-1, 1, net.in_size)
    a = net.apply(params, obs)
    assert a.shape == (1,) and bool(jnp.all(jnp.abs(a) <= 1))


def test_resume_after_kill_matches_uninterrupted(full_run, tmp_path):
    out_full, _ = full_run
    # "Killed" after epoch 1: a run of 2 epochs leaves train_state at epoch 1; the resumed run
    # must be started with the same settings, so we write the 4-epoch run.json by hand.
    runner.train_run(ENV, "toy", tmp_path, epochs=2, seed=3, progress=False)
    doc = json.loads((tmp_path / "run.json").read_text())
    doc["config"]["epochs"] = 4
    (tmp_path / "run.json").write_text(json.dumps(doc))
    s = runner.train_run(ENV, "toy", tmp_path, epochs=4, seed=3, progress=False, resume=True)
    assert s["resumed"]
    a = checkpoint.load_policy(out_full)[1]
    b = checkpoint.load_policy(tmp_path)[1]
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    m_full, m_res = (list(csv.DictReader(open(d / "metrics.csv"))) for d in (out_full, tmp_path))
    assert len(m_full) == len(m_res) == 4
    for a_row, b_row in zip(m_full, m_res):
        for k in ("epoch", "env_steps", "return"):
            assert a_row[k] == b_row[k], (k, a_row, b_row)


def test_existing_run_needs_resume_and_same_settings(full_run):
    out, _ = full_run
    with pytest.raises(runner.RunError, match="--resume"):
        runner.train_run(ENV, "toy", out, epochs=4, seed=3, progress=False)
    with pytest.raises(runner.RunError, match="different settings.*seed"):
        runner.train_run(ENV, "toy", out, epochs=4, seed=4, progress=False, resume=True)


def test_config_overrides_and_errors():
    cfg = runner.make_config("toy", ENV, runner.parse_overrides(["lr=0.5", "epochs=7"]))
    assert cfg.lr == 0.5 and cfg.epochs == 7
    with pytest.raises(runner.RunError, match="no field 'learning_rate'"):
        runner.make_config("toy", ENV, {"learning_rate": 1.0})
    with pytest.raises(runner.RunError, match="unknown algorithm 'sac'"):
        runner.algorithm("sac")
    with pytest.raises(runner.RunError, match="field=value"):
        runner.parse_overrides(["lr"])


def test_checkpoint_errors(tmp_path):
    with pytest.raises(checkpoint.CheckpointError, match="no checkpoint.json"):
        checkpoint.load_policy(tmp_path)
    (tmp_path / "checkpoint.json").write_text("{not json")
    with pytest.raises(checkpoint.CheckpointError, match="not valid JSON"):
        checkpoint.load_policy(tmp_path)
    net = make_policy(3, 1, (4,))
    bad = jax.tree.map(lambda x: x * jnp.nan, net.init(jax.random.key(0)))
    with pytest.raises(ValueError, match="non-finite"):
        checkpoint.save_policy(tmp_path / "p", net, bad)


def test_zero_last_network_outputs_zero_and_round_trips(tmp_path):
    net = make_network(4, 2, NetworkConfig(hidden=(8,), output="linear", zero_last=True))
    params = net.init(jax.random.key(1))
    assert bool(jnp.all(net.apply(params, jnp.ones((5, 4))) == 0))
    checkpoint.save_policy(tmp_path, net, params, algo="residual")
    net2, params2, _ = checkpoint.load_policy(tmp_path)
    assert net2.config == net.config and bool(jnp.all(net2.apply(params2, jnp.ones(4)) == 0))


def test_train_state_keeps_rng_keys_and_empty_arrays(tmp_path):
    # An mjx.Data in a trainer's state carries zero-size arrays, which orbax cannot store alone.
    ck = checkpoint.TrainStateCheckpointer(tmp_path)
    state = {"rng": jax.random.key(5), "x": jnp.arange(3.0), "act": jnp.zeros((0,))}
    ck(0, state, {"epoch": [0.0]})
    got, hist = checkpoint.TrainStateCheckpointer(tmp_path).restore(
        jax.tree.map(jnp.zeros_like, {**state, "rng": jax.random.key(0)}))
    assert hist == {"epoch": [0.0]} and got["act"].shape == (0,)
    np.testing.assert_array_equal(got["x"], state["x"])
    np.testing.assert_array_equal(jax.random.key_data(got["rng"]), jax.random.key_data(state["rng"]))


def test_metrics_writer_rewrite_drops_epochs_past_the_restored_state(tmp_path):
    w = MetricsWriter(tmp_path, tensorboard=False)
    for e in range(3):
        w.write(e, {"epoch": e, "return": float(e)})
    w.rewrite({"epoch": [0.0], "return": [0.0]})
    w.write(1, {"epoch": 1, "return": 1.0})
    assert (tmp_path / "metrics.csv").read_text().splitlines() == ["epoch,return", "0.0,0.0",
                                                                   "1.0,1.0"]


# ------------------------------------------------------------------ the System a policy learnt in
def test_policy_trained_in_a_system_is_evaluated_in_that_system(tmp_path):
    """Acceptance (issue 18): a policy trained in an identified ``System`` (heavier, more damped
    pendulum, two steps of action latency), saved, and run by ``twinrl eval --checkpoint DIR``,
    runs in that system, not in the task's nominal simulator."""
    from twinrl import cli, envs
    from twinrl.envs import System, system_of
    from twinrl.learn.common import make_evaluator

    nominal = System.nominal(ENV)
    p = nominal.params
    system = nominal.replace(params=p.replace(mass=np.asarray(p.mass) * 1.7,
                                              damping=np.asarray(p.damping) + 0.05), latency=2)
    run = tmp_path / "run"
    runner.train_run(ENV, "toy", run, epochs=2, seed=1, progress=False,
                     env=envs.make(ENV, system=system))
    saved = checkpoint.load_system(run)
    assert saved.to_json() == system.to_json()            # exact, latency included
    assert (run / "policy" / "system.json").exists()

    out = tmp_path / "eval"
    assert cli.main(["eval", "--checkpoint", str(run), "--episodes", "3", "--no-video",
                     "--seed", "4", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["system"]["from"] == "checkpoint"
    assert summary["system"]["latency"] == 2
    assert summary["system"]["params"] == system.to_json()["params"]
    # the eval env the runner rebuilds is that system; its returns are that system's, and
    # differ from the same policy's in the nominal simulator
    net, params, meta = checkpoint.load_policy(run)
    rebuilt = runner.env_from_meta(meta, saved)
    assert rebuilt.latency == 2 and system_of(rebuilt).to_json() == system.to_json()
    key = jax.random.key(4)
    in_system = np.asarray(make_evaluator(envs.make(ENV, system=system), net.apply, 3)(params, key))
    in_nominal = np.asarray(make_evaluator(envs.make(ENV), net.apply, 3)(params, key))
    np.testing.assert_allclose(summary["returns"], in_system, rtol=1e-5)
    assert np.max(np.abs(in_system - in_nominal)) > 1e-3 * max(1.0, np.max(np.abs(in_nominal)))


def test_checkpoint_without_a_system_is_evaluated_in_the_nominal_task(full_run, tmp_path):
    out, _ = full_run
    assert checkpoint.load_system(out).latency == 0      # trained on envs.make(ENV): nominal
    (out / "policy" / "system.json").rename(tmp_path / "kept.json")
    try:
        assert checkpoint.load_system(out) is None       # written before checkpoints had one
        s = runner.eval_run(out, tmp_path / "eval", episodes=1, video=False, progress=False)
        assert s["system"]["from"].startswith("nominal") and s["system"]["latency"] == 0
    finally:
        (tmp_path / "kept.json").rename(out / "policy" / "system.json")


def test_progress_bar_shows_only_reported_finite_figures():
    from twinrl.learn.runner import progress_figures
    assert progress_figures({"return": 184.04}) == "return 184.04"  # PPO: no 'grad nan'
    assert progress_figures({"return": 1.0, "grad_norm": float("nan")}) == "return 1.00"
    assert progress_figures({"return": 2.0, "grad_norm": 0.5}) == "return 2.00  grad 5.00e-01"


def test_training_in_a_log_prints_progress_lines(tmp_path, monkeypatch, capsys):
    # no terminal (a log, a pipe): no live bar, which a log shows nothing of, but dim lines --
    # the first while the first epoch compiles, then the epochs with their figures
    from twinrl import progress

    monkeypatch.setattr(progress, "QUIET_FOR", 0.0)
    lines = []
    real = progress.ProgressLines._print
    monkeypatch.setattr(progress.ProgressLines, "_print",
                        lambda self, msg: (lines.append(msg), real(self, msg)))
    monkeypatch.setattr(progress.ProgressLines, "tick", lambda self, msg: self(msg))  # each
    runner.train_run(ENV, "toy", tmp_path / "run", epochs=3, seed=0, progress=True)
    assert lines[0] == "tracing and compiling the first epoch ..."
    assert [m.split()[:2] for m in lines[1:]] == [["epoch", "1/3"], ["epoch", "2/3"],
                                                  ["epoch", "3/3"]]
    assert all("return" in m for m in lines[1:])
    assert "train toy on pendulum_swingup [" in capsys.readouterr().out
