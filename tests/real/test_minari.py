"""Minari both ways (``twinrl.real.dataset.minari``, ``twinrl export``, ``--from minari:NAME``):
a twinrl dataset survives the trip through Minari bit for bit; a Minari dataset written by someone
else with Minari's own API is read where its spaces fit a task and refused in one line where not.

Tiny datasets and no compiles: every Minari dataset lives in the test's own MINARI_DATASETS_PATH.
"""

from __future__ import annotations

import json
import re

import gymnasium as gym
import minari  # the `minari` extra is part of `dev`: `make test` always has it
import numpy as np
import pytest

from twinrl import cli
from twinrl.real.dataset import DatasetError, DatasetMismatch, DatasetWriter, read
from twinrl.real.dataset.minari import (MinariUnavailable, find_dataset, import_minari,
                                        read_minari, to_minari)

TASK = "pendulum_swingup"  # observation (4,), full state (2,), action (1,) in [-1, 1]
IMAGES = {"rgb": (4, 5, 3), "depth": (4, 5), "segmentation": (4, 5), "rgb/wrist": (2, 3, 3)}


@pytest.fixture(autouse=True)
def minari_root(tmp_path, monkeypatch):
    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return root


def _images(rng):
    return {"rgb": rng.integers(0, 256, IMAGES["rgb"], dtype=np.uint8),
            "depth": rng.random(IMAGES["depth"], dtype=np.float32),
            "segmentation": rng.integers(-1, 9, IMAGES["segmentation"], dtype=np.int32),
            "rgb/wrist": rng.integers(0, 256, IMAGES["rgb/wrist"], dtype=np.uint8)}


def recorded(path, images=True):
    """Four episodes ending each way twinrl records: terminated, truncated (with a lost record
    between two steps: its next_obs is not the next obs), ended by the operator, and one left
    open by a writer that closed mid-episode."""
    rng = np.random.default_rng(0)
    plans = [(3, "terminated"), (4, "truncated"), (2, "end"), (2, "open")]
    with DatasetWriter(path, env=TASK, obs_shape=4, action_shape=1,
                       image_shapes=IMAGES if images else None, obs_dtype=np.float32,
                       action_dtype=np.float32, metadata={"note": "round trip", "k": [1, 2]},
                       sync="none") as w:
        for length, ending in plans:
            obs = rng.standard_normal(4).astype(np.float32)
            for t in range(length):
                nxt = rng.standard_normal(4).astype(np.float32)
                last = t == length - 1
                w.add(obs, rng.uniform(-1, 1, 1).astype(np.float32), float(rng.standard_normal()),
                      nxt, last and ending == "terminated", last and ending == "truncated",
                      info={"t": t, "energy": float(rng.random()), **({"tag": "x"} if t else {})},
                      images=_images(rng) if images else None)
                obs = rng.standard_normal(4).astype(np.float32) if (ending, t) == (
                    "truncated", 1) else nxt
            if ending == "end":
                w.end_episode()
    return read(path)


def assert_same(a, b):
    assert a.meta == b.meta
    for name in ("obs", "action", "reward", "next_obs", "terminated", "truncated", "episode_id",
                 "step", "time", "episode_starts", "episode_ends", "episode_complete"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert a.info == b.info
    assert sorted(a.images) == sorted(b.images)
    for k in a.images:
        assert a.images[k].dtype == b.images[k].dtype, k
        np.testing.assert_array_equal(a.images[k], b.images[k], err_msg=k)


def test_round_trip_loses_nothing(tmp_path, minari_root):
    original = recorded(tmp_path / "ds")
    assert original.episode_complete.tolist() == [True, True, True, False]
    to_minari(original, "twinrl/pendulum/rt", twin_seeds=[7])
    back = read_minari("twinrl/pendulum/rt")  # the highest local version: -v0
    assert_same(original, back)

    # what Minari itself sees: its own reader, its conventions
    mds = minari.load_dataset("twinrl/pendulum/rt-v0")
    assert mds.total_episodes == 5  # the truncated episode is cut at its lost record
    assert mds.total_steps == len(original)
    assert mds.observation_space == gym.spaces.Box(-np.inf, np.inf, (4,), np.float32)
    assert mds.action_space == gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
    first = mds[0]
    np.testing.assert_array_equal(first.observations[:-1], original.obs[:3])
    np.testing.assert_array_equal(first.observations[-1], original.next_obs[2])
    assert first.terminations.tolist() == [False, False, True]
    np.testing.assert_array_equal(first.infos["images"]["rgb:wrist"][1:],
                                  original.images["rgb/wrist"][:3])
    meta = mds.storage.metadata["twinrl"]
    assert (meta["task"], meta["twin_seed"], meta["twin_seeds"]) == (TASK, 7, [7])
    # the public seed only: nothing of the twin's hidden perturbation or its secret
    text = json.dumps(meta).lower()
    assert not any(w in text for w in ("perturb", "secret", "salt"))


def test_round_trip_of_any_env_shape_and_dtype(tmp_path):
    with DatasetWriter(tmp_path / "ds", env="my_robot", obs_shape=(2, 3), action_shape=2,
                       obs_dtype=np.int32, action_dtype=np.float64, sync="none") as w:
        for t in range(3):
            w.add(np.full((2, 3), t), [0.5 * t, -t], t, np.full((2, 3), t + 1), False, t == 2)
    original = read(tmp_path / "ds")
    to_minari(original, "robot-v0")
    assert_same(original, read_minari("robot-v0"))
    with pytest.raises(DatasetMismatch, match="recorded on 'my_robot', not 'push'"):
        read_minari("robot-v0", task="push")


def test_a_name_is_written_once_and_a_missing_one_lists_the_local_ones(tmp_path):
    data = recorded(tmp_path / "ds", images=False)
    to_minari(tmp_path / "ds", "mine-v2")
    with pytest.raises(DatasetError, match="'mine-v2' already exists"):
        to_minari(data, "mine-v2")
    with pytest.raises(DatasetError,
                       match=r"no Minari dataset 'other-v0' .*local datasets: mine-v2"):
        read_minari("other")
    with pytest.raises(DatasetError, match="not a Minari dataset id"):
        to_minari(data, "bad name!")
    assert find_dataset("mine")[0] == "mine-v2"
    to_minari(data, "mine-v10")
    assert find_dataset("minari:mine")[0] == "mine-v10"  # the highest version, by number


class Toy(gym.Env):
    """Someone else's environment: twinrl knows nothing of it but its spaces."""

    def __init__(self, obs_space, horizon=6):
        self.observation_space = obs_space
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.horizon = horizon

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return self.observation_space.sample(), {"energy": 0.0}

    def step(self, action):
        self.t += 1
        obs = self.observation_space.sample()
        term = self.t == self.horizon and self.np_random.random() < 0.5
        return obs, float(self.np_random.random()), term, self.t == self.horizon and not term, {
            "energy": float(np.sum(action))}


def collect_foreign(name, obs_space, episodes=3):
    """A Minari dataset made with Minari's own DataCollector, not through twinrl."""
    env = minari.DataCollector(Toy(obs_space), record_infos=True)
    env.observation_space.seed(0)
    env.action_space.seed(0)
    for e in range(episodes):
        env.reset(seed=e)
        done = False
        while not done:
            _, _, term, trunc, _ = env.step(env.action_space.sample())
            done = term or trunc
    with pytest.warns(UserWarning):  # Minari asks for an author, a code permalink, ...
        env.create_dataset(name)
    env.close()
    return minari.load_dataset(name)


def test_a_foreign_dataset_that_fits_a_task_is_read():
    box = gym.spaces.Box(-np.inf, np.inf, (4,), np.float32)
    theirs = collect_foreign("someone/toy-v0", box)
    data = read_minari("someone/toy-v0", task=TASK)
    assert data.meta["env"] == TASK and data.meta["metadata"] == {"source": "minari:someone/toy-v0"}
    assert data.num_episodes == 3 and data.episode_complete.all()
    for ep, mine in zip(theirs.iterate_episodes(), data.episodes()):
        np.testing.assert_array_equal(mine.obs, ep.observations[:-1])
        np.testing.assert_array_equal(mine.next_obs, ep.observations[1:])
        np.testing.assert_array_equal(mine.action, ep.actions)
        np.testing.assert_array_equal(mine.reward, ep.rewards)
        np.testing.assert_array_equal(mine.terminated, ep.terminations)
        np.testing.assert_array_equal(mine.truncated, ep.truncations)
        assert mine.step.tolist() == list(range(len(ep)))
        assert [i["energy"] for i in mine.info] == ep.infos["energy"][1:].tolist()
    assert data.obs.dtype == np.float32


def test_a_foreign_dataset_of_full_states_built_from_buffers_is_read_as_states():
    from minari.data_collector import EpisodeBuffer

    rng = np.random.default_rng(1)
    buffers = [EpisodeBuffer(observations=rng.standard_normal((6, 2)),
                             actions=rng.uniform(-1, 1, (5, 1)), rewards=rng.random(5),
                             terminations=[False] * 4 + [True], truncations=[False] * 5)]
    with pytest.warns(UserWarning):
        minari.create_dataset_from_buffers(
            "states-v1", buffers, observation_space=gym.spaces.Box(-np.inf, np.inf, (2,)),
            action_space=gym.spaces.Box(-1.0, 1.0, (1,)))
    data = read_minari("states", task=TASK)
    assert data.meta["metadata"]["observation"] == "state"
    assert data.obs.dtype == np.float32 and data.obs.shape == (5, 2)  # Box's default dtype
    np.testing.assert_array_equal(data.next_obs[-1], buffers[0].observations[-1].astype(np.float32))


@pytest.mark.parametrize("space, reason", [
    (gym.spaces.Box(-np.inf, np.inf, (5,), np.float32),
     "observation shape (5,) fits neither pendulum_swingup's observation (4,) nor its full "
     "state (2,)"),
    (gym.spaces.Dict({"state": gym.spaces.Box(-1, 1, (4,), np.float32)}),
     "observation space is Dict"),
])
def test_a_foreign_dataset_that_does_not_fit_is_refused_in_one_line(space, reason):
    collect_foreign("misfit-v0", space, episodes=1)
    with pytest.raises(DatasetMismatch, match=re.escape(reason)) as e:
        read_minari("misfit-v0", task=TASK)
    assert "\n" not in str(e.value)
    with pytest.raises(DatasetMismatch, match="names no twinrl task"):
        read_minari("misfit-v0")


def test_import_into_a_twinrl_directory_keeps_values_and_boundaries(tmp_path):
    original = recorded(tmp_path / "ds")
    to_minari(original, "imp-v0")
    data = import_minari("imp", tmp_path / "out", task=TASK)
    again = read(tmp_path / "out")
    assert again.meta["metadata"] == {**original.meta["metadata"], "source": "minari:imp-v0"}
    for name in ("obs", "action", "reward", "next_obs", "terminated", "truncated", "step"):
        np.testing.assert_array_equal(getattr(again, name), getattr(data, name), err_msg=name)
        assert getattr(again, name).dtype == getattr(original, name).dtype
    assert again.info == original.info
    np.testing.assert_array_equal(again.images["depth"], original.images["depth"])
    assert (again.episode_ends - again.episode_starts).tolist() == [3, 4, 2, 2]
    with pytest.raises(DatasetError, match="already holds a dataset"):
        import_minari("imp", tmp_path / "out", task=TASK)


def run(capsys, *args):
    code = cli.main([str(a) for a in args])
    out = capsys.readouterr()
    return code, out.out, out.err


def one_line(err, *fragments):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    for f in fragments:
        assert f in lines[0], lines[0]


def test_cli_export_then_collect_from_minari(tmp_path, capsys, minari_root):
    recorded(tmp_path / "run" / "dataset", images=False)
    (tmp_path / "run" / "eval").mkdir()
    (tmp_path / "run" / "eval" / f"twin-{TASK}-seed3.json").write_text("{}")
    code, out, err = run(capsys, "export", tmp_path / "run", "--to", "minari", "cli-v0",
                         "--minari-root", tmp_path / "elsewhere")
    assert code == 0, err
    assert not minari_root.exists() or not any(minari_root.iterdir())
    meta = json.loads((tmp_path / "elsewhere" / "cli-v0" / "data" / "metadata.json").read_text())
    assert meta["twinrl"]["twin_seed"] == 3 and meta["twinrl"]["task"] == TASK
    # import only (no episodes recorded, no twin started), then a re-run keeps what is there
    for _ in range(2):
        code, out, err = run(capsys, "collect", "--env", TASK, "--from", "minari:cli",
                             "--minari-root", tmp_path / "elsewhere", "--seed", "3",
                             "--episodes", "0", "--out", tmp_path / "c")
        assert code == 0, err
    assert read(tmp_path / "c" / "dataset").num_episodes == 4


@pytest.mark.parametrize("args, fragments", [
    (["export", "{tmp}/nothing", "--to", "minari", "x-v0"], ["no dataset at"]),
    (["export", "{tmp}/run", "--to", "minari", "bad name"], ["not a Minari dataset id"]),
    (["export", "{tmp}/run", "--to", "minari", "pend-v0"], ["'pend-v0' already exists"]),
    (["sysid", "--env", TASK, "--from", "minari:nosuch"],
     ["--from minari:nosuch", "no Minari dataset 'nosuch-v0'", "local datasets: pend-v0"]),
    (["sysid", "--env", "cartpole_swingup", "--from", "minari:pend"],
     ["was recorded on 'pendulum_swingup', not 'cartpole_swingup'"]),
    (["collect", "--env", "cartpole_swingup", "--episodes", "1", "--from", "minari:pend"],
     ["was recorded on 'pendulum_swingup', not 'cartpole_swingup'"]),
    (["collect", "--env", TASK, "--episodes", "1", "--from", "{tmp}/run"],
     ["--from takes minari:NAME"]),
    (["collect", "--env", TASK, "--episodes", "1", "--from", "minari:pend", "--seed", "1"],
     ["recorded on real twin seed 3", "--seed 3"]),
    (["collect", "--env", TASK, "--episodes", "1", "--from", "minari:pend", "--seed", "3",
      "--images"], ["holds no images"]),
])
def test_cli_bad_minari_input_is_one_line_and_exit_2(tmp_path, capsys, args, fragments):
    recorded(tmp_path / "run" / "dataset", images=False)
    to_minari(tmp_path / "run" / "dataset", "pend", twin_seeds=[3])
    code, _, err = run(capsys, *(a.format(tmp=tmp_path) for a in args))
    assert code == 2
    one_line(err, *fragments)


def test_without_the_extra_the_error_names_it(tmp_path, capsys, monkeypatch):
    recorded(tmp_path / "ds", images=False)
    monkeypatch.setitem(__import__("sys").modules, "minari", None)  # `import minari` fails
    with pytest.raises(ImportError, match=r"pip install 'twinrl\[minari\]'"):
        read_minari("anything")
    code, _, err = run(capsys, "export", tmp_path / "ds", "--to", "minari", "x-v0")
    assert code == 2
    one_line(err, "twinrl export: error: Minari datasets need the `minari` extra")
    assert issubclass(MinariUnavailable, DatasetError)


def test_the_public_twin_seed_comes_from_a_collect_or_run_directory(tmp_path):
    from twinrl.cli.export import twin_seeds

    (tmp_path / "collect" / "eval").mkdir(parents=True)
    for seed in (5, 2):
        (tmp_path / "collect" / "eval" / f"twin-{TASK}-seed{seed}.json").write_text("{}")
    (tmp_path / "collect" / "eval" / "twin-push-seed9.json").write_text("{}")
    assert twin_seeds(tmp_path / "collect", TASK) == [2, 5]
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "loop.json").write_text(json.dumps({"kind": "run", "seed": 4}))
    assert twin_seeds(tmp_path / "run", TASK) == [4]
    assert twin_seeds(tmp_path / "nothing", TASK) == []
