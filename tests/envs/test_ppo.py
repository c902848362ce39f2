"""Brax's own PPO trainer runs on our tasks, unmodified.

``brax.training.agents.ppo.train.train`` wraps our ``Env`` with Brax's ``wrap`` (vmap, episode,
auto-reset), so this is the compatibility test of the ``Env``/``State`` contract. Tiny settings:
8 environments, 20-step episodes, 640 environment steps; the time each task took (compile
included) is printed, not asserted (timings belong in bench/).
"""

import time

import numpy as np
import pytest
from brax.training.agents.ppo import train as ppo

from twinrl import envs


# Two tasks, one per kind: cartpole_swingup (smooth, 1-D action, the loop's default learner runs
# Brax PPO on it) and push (contacts, 2-D action). cartpole_balance is cartpole_swingup's model and
# step with another reset (tests/envs/test_envs.py::test_balance_and_swingup_share_a_model);
# pendulum_swingup is a third smooth 1-D task on the same Env/State contract (its compile, 41 s,
# was the suite's budget, not coverage).
@pytest.mark.parametrize("name", ["cartpole_swingup", "push"])
def test_brax_ppo_trains_unmodified(name):
    env = envs.make(name)
    progress = []
    t0 = time.perf_counter()
    make_policy, params, metrics = ppo.train(
        environment=env, num_timesteps=640, episode_length=20, num_envs=8, batch_size=8,
        num_minibatches=2, unroll_length=5, num_updates_per_batch=1, num_evals=1,
        num_eval_envs=8, normalize_observations=True, use_pmap_on_reset=False, seed=0,
        progress_fn=lambda step, m: progress.append(step))
    print(f"\nPPO {name}: {time.perf_counter() - t0:.1f} s (compile included)")
    ret = float(metrics["eval/episode_reward"])
    assert np.isfinite(ret) and 0.0 <= ret <= 20.0
    for term in env.reward_term_names:
        assert np.isfinite(float(metrics[f"eval/episode_reward/{term}"]))
    assert progress and progress[-1] >= 640
    assert callable(make_policy(params, deterministic=True))
