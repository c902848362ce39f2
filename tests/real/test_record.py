"""``twinrl.real.record``: the one routine that records episodes on a real twin. A stand-in twin
(a counter with a known return) checks what every caller relies on: each episode reset with the
caller's seed, its policy asked for after the reset, every transition written with its flags,
``steps`` cutting episodes short, and ``episode_seeds`` being ``twinrl collect``'s scheme."""

import numpy as np

from twinrl.real.dataset import DatasetWriter, read
from twinrl.real.record import episode_seeds, record_episodes


class CountingTwin:
    """Observation: the step count; reward 1 a step; truncated after ``length`` steps."""

    def __init__(self, length=4):
        self.length, self.resets, self.t = length, [], 0

    def reset(self, seed=None):
        self.resets.append(seed)
        self.t = 0
        return np.zeros(1, np.float32), {}

    def step(self, action):
        self.t += 1
        return (np.full(1, self.t, np.float32), 1.0, False, self.t >= self.length,
                {"t": self.t, "skipped": [1, 2]})


def test_episodes_are_reset_seeded_and_recorded(tmp_path):
    twin, asked = CountingTwin(), []

    def policy(e):
        asked.append((e, len(twin.resets)))  # after episode e's reset
        return lambda obs, t: np.full(1, e + t, np.float32)

    with DatasetWriter(tmp_path, env="fake", obs_shape=(1,), action_shape=(1,)) as w:
        got = record_episodes(twin, [2, 3], policy, lambda e: 100 + e, writer=w, keep=True)
    assert twin.resets == [102, 103] and asked == [(2, 1), (3, 2)]
    assert [(r.episode, r.ret, r.steps) for r in got] == [(2, 4.0, 4), (3, 4.0, 4)]
    np.testing.assert_array_equal(got[1].transitions["action"][:, 0], [3, 4, 5, 6])
    data = read(tmp_path)
    assert len(data) == 8 and int(np.sum(data.episode_complete)) == 2
    np.testing.assert_array_equal(data.action[:4, 0], [2, 3, 4, 5])


def test_steps_cuts_an_episode_and_marks_it_truncated(tmp_path):
    twin = CountingTwin(length=10)
    with DatasetWriter(tmp_path, env="fake", obs_shape=(1,), action_shape=(1,)) as w:
        got = record_episodes(twin, range(2), lambda e: lambda o, t: [0.0], lambda e: e,
                              writer=w, steps=3)
    assert [r.steps for r in got] == [3, 3] and got[0].transitions is None
    data = read(tmp_path)
    assert len(data) == 6 and int(np.sum(data.episode_complete)) == 2


def test_episode_seeds_are_twinrl_collects_scheme():
    seq = np.random.SeedSequence([7, 5])
    reset, rng = episode_seeds(7, 5)
    assert reset == int(seq.generate_state(1)[0])
    assert rng.integers(0, 2**31) == np.random.default_rng(seq.spawn(1)[0]).integers(0, 2**31)
    assert episode_seeds(7, 6)[0] != reset
