"""The tuned-config table: per-algorithm, per-task overrides of each trainer's config defaults.

One table of one shape, ``TUNED[algo][task] -> {field: value}``, kept apart from the trainers and
from the task configs (MuJoCo Playground's habit). ``twinrl.learn.runner.make_config`` applies it
(class defaults, then ``overrides(algo, task)``, then the algorithm entry's own, e.g. ``pods2``:
order 2, then the user's), and so do ``baselines.ppo_config``/``apg_config``. Each entry says
what it was measured on (``bench/learn.py``-style runs on one CPU core unless noted). An
algorithm or task without an entry runs with its config's defaults.
"""

from __future__ import annotations

import copy
from typing import Any

__all__ = ["TUNED", "overrides"]

TUNED: dict[str, dict[str, dict[str, Any]]] = {
    # ------------------------------------------------------------------ PODS (learn.pods)
    "pods": {
        "pendulum_swingup": {},
        # The critic (pods module docstring): without it pods stalls at ~85 (30 epochs). With it
        # the 10-epoch mean is >= 130 from epoch 35 / 97 / 39 (seeds 0 / 1 / 2; final 176.7 at
        # 80 / 133.0 at 150 / 185.8 at 80): 150 epochs, ~3 min on one core.
        "cartpole_swingup": {"critic": True, "epochs": 150},
        "push": {"horizon": 20},
    },
    "pods2": {
        # The damped Gauss-Newton step with regularization 1e-2 is ~g / 1e-2 where the reward is
        # flat in the action (hanging: the upright factor zeroes the control cost's curvature),
        # more than the policy can follow; with 1.0 and the critic, seed 0 solves (return 160.3
        # at epoch 60, 10-epoch mean >= 130 from epoch 16); without the critic it stays at
        # 120-126.
        "pendulum_swingup": {"critic": True, "regularization": 1.0, "epochs": 60},
        # regularization 1.0 (1e-2, and 0.3 or 0.1 with max_step_norm 2, collapse to ~0 and
        # recover only partly); 10-epoch mean >= 130 from epoch 44 / 157 / 111 (seeds 0 / 1 / 2;
        # final 160.1 at 100 / 127.8 at 200 / 137.7 at 200): 200 epochs, ~5 min on one core.
        "cartpole_swingup": {"critic": True, "regularization": 1.0, "epochs": 200},
        "push": {"horizon": 20},
    },
    # ------------------------------------------------------------------ HDS (learn.hds)
    "hds": {
        "pendulum_swingup": {},
        # The critic (``PODSConfig.critic``), slower noise decay, and the annealed step size kept
        # in [1, 10]: its floor is PODS's fixed step (1.0, whose line search already tries down to
        # 1/128). With the floor at 0.25 the chain settled there on seed 1 and the return stayed
        # at ~80 for 120 epochs (0.05: 92.9 at epoch 80; without the critic the best was 117.2 in
        # 300). With [1, 10]: 130 first at epoch 24 / 31 / 23 and the 10-epoch mean >= 130 from
        # epoch 31 / 37 / 38 (seeds 0 / 1 / 2; final 198.1 / 165.3 / 170.3 at 150; ~175 s on one
        # core each); the chain wanders up to 7-10 in the first epochs and sits near 1-2.3 later.
        "cartpole_swingup": {"critic": True, "step_size_bounds": (1.0, 10.0),
                             "noise_decay": 0.97, "epochs": 150},
        "push": {"horizon": 20},
    },
    # ------------------------------------------------------------------ SHAC (learn.shac)
    "shac": {
        "pendulum_swingup": {"epochs": 150},
        # SHAC's own cartpole learning rates (actor 1e-2, critic 1e-3). With the defaults (2e-3
        # for both) the return stalled at 73 after 300 epochs; either change alone stayed below
        # 95 after 200 epochs; both together: final return 134.9 / 156.9 / 188.5 (seeds 0 / 1 /
        # 2; mean of the last 50 epochs 134.6 / 165.9 / 188.4), 10-epoch mean >= 130 from epoch
        # 75 / 139 / 23.
        # horizon 64 (SHAC's own 32 before): the return of 192.3 PPO ends at (one run) is reached at
        # epoch 153 / 87 / never (seeds 0 / 1 / 2; best 197.7 / 199.8 / 187.5, final 195.4 /
        # 193.8 / 175.6 at 300), where with 32 no seed reached it (best 165.8 on seed 0).
        # critic_iterations 4 (16 before): the critic's 64 minibatch steps were 40 % of an epoch
        # (0.168 -> 0.103 s on 2 cores) and the return learned per epoch did not suffer: PPO's
        # final 193.4 reached at epoch never / 148 / 188 (16: 153 / 87 / never). No setting tried
        # reached it on 3 of 3 seeds (docs/known-limits.md: horizon 32, 2 critic iterations or
        # 2 minibatches, 128 or 256 environments, 100 or 150 epochs, actor_lr 2e-2).
        "cartpole_swingup": {"epochs": 300, "actor_lr": 1e-2, "critic_lr": 1e-3, "horizon": 64,
                             "critic_iterations": 4},
    },
    # ------------------------------------------------------------------ Brax (learn.baselines)
    "ppo": {
        # entropy_cost 0.03 (default 0.01): on the simulator identified from cartpole real twin 2
        # (``twinrl run --seed 2``), PPO with 0.01 stalled on 3 of 4 seeds (sim returns 88, 94,
        # 41; seed 5: 170.5) -- the policy's noise collapses before it finds the swing-up. With
        # 0.03 the three failing seeds reached 169.5, 167.3 and 166.7 (3.5 M steps each).
        "cartpole_swingup": {"entropy_cost": 0.03},
        "pendulum_swingup": {},
    },
    "apg": {"cartpole_swingup": {}, "pendulum_swingup": {}},
}
"""``TUNED[algo][task]``: overrides of the algorithm's config defaults for the task (module
docstring). Values are plain config fields; a nested config takes a dict of its fields."""


def overrides(algo: str, task: str) -> dict[str, Any]:
    """A copy of ``TUNED[algo][task]`` (``{}`` where there is no entry), safe to modify."""
    return copy.deepcopy(TUNED.get(algo, {}).get(task, {}))
