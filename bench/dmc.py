"""Learning on the DeepMind Control Suite tasks (``dmc/``) at a fixed budget, beside published
Control Suite figures.

For every task and algorithm (Brax PPO, ``ppo``; twinrl's first-order learners ``shac`` and
``hds``), over ``--seeds`` seeds, one ``twinrl.learn.runner.train_run`` with the CLI's configs
(``make_config``: class defaults, ``tuned.TUNED``, then this bench's ``--set`` and budget): the
final return (deterministic policy, over the evaluation episodes; a Control Suite episode is
1000 steps with per-step reward in [0, 1], so returns are in [0, 1000]), the env steps and the
wall clock. The table puts beside them the published figure for Brax PPO on the same suite task
where one is given in ``PUBLISHED`` (source and its settings recorded with it); ``--budget``
steps on a 2-core CPU is far below a published budget (MuJoCo Playground trains PPO for 60 M
steps, 2048 environments, on a GPU), so the columns answer "where does a CPU budget get" rather
than "do we match".

    python bench/dmc.py --out bench/results                       # every task, ppo+shac, 1 seed
    python bench/dmc.py --tasks dmc/cartpole-swingup --algos ppo --budget 200000 --out /tmp/dmc

Writes ``dmc.json`` (``bench/benchio.py``'s ``meta`` + one row per run + the settings) and
prints the table; each run's own directory (metrics.csv, curve.png, policy) is under
``--out/dmc_runs/``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, jaxconfig)
import numpy as np

from twinrl import envs
from twinrl.learn import runner
from twinrl.report import print_table
from benchio import RESULTS, write_result  # noqa: E402  (bench/benchio.py)

PLAYGROUND = ("https://github.com/google-deepmind/mujoco_playground/blob/main/"
              "mujoco_playground/config/dm_control_suite_params.py")
PAPER = "https://arxiv.org/abs/2502.08844"
PLAYGROUND_PPO = {"num_timesteps": 60_000_000, "num_envs": 2048, "batch_size": 1024,
                  "unroll_length": 30, "num_minibatches": 32, "num_updates_per_batch": 16,
                  "discounting": 0.995, "learning_rate": 1e-3, "entropy_cost": 1e-2,
                  "reward_scaling": 10.0, "episode_length": 1000}
"""MuJoCo Playground's Brax PPO settings for the Control Suite (``PLAYGROUND``; FingerSpin:
discounting 0.95; PendulumSwingup: action repeat 4, 4 updates per batch)."""

PUBLISHED: dict[str, dict] = {
    name: {"algo": "Brax PPO (MuJoCo Playground)", "return": None,
           "steps": PLAYGROUND_PPO["num_timesteps"], "source": PAPER, "settings": PLAYGROUND}
    for name in ("dmc/cartpole-swingup", "dmc/pendulum-swingup", "dmc/reacher-easy",
                 "dmc/finger-spin", "dmc/cheetah-run", "dmc/walker-walk")
}
"""The published figure per task. MuJoCo Playground's paper reports its Control Suite PPO
results as learning curves (a figure, no table), so ``return`` stays None here rather than a
number read off a plot; the settings (``PLAYGROUND_PPO``) and the source are recorded."""

TASKS = tuple(PUBLISHED)
ALGOS = ("ppo", "shac", "hds")
# A CPU budget: Brax PPO with few environments and Playground's discount, reward scale and
# unroll; evaluations on few episodes (1000 steps each).
PPO_CPU = {"num_envs": 64, "batch_size": 64, "num_minibatches": 8, "unroll_length": 30,
           "num_updates_per_batch": 4, "discounting": 0.995, "reward_scaling": 10.0,
           "num_eval_envs": 8, "num_evals": 5}
SHAC_CPU = {"num_envs": 16}
HDS_CPU: dict = {}


def run(task: str, algo: str, seed: int, budget: int, epochs: int, out: Path,
        extra: dict) -> dict:
    """One training run at the budget; the row of the table."""
    overrides = {"ppo": PPO_CPU, "shac": SHAC_CPU, "hds": HDS_CPU}[algo] | extra
    if algo == "ppo":
        length = {"steps": budget}
    else:
        length = {"epochs": epochs}
    t0 = time.perf_counter()
    run_dir = out / "dmc_runs" / f"{task.replace('/', '_')}-{algo}-{seed}"
    try:
        s = runner.train_run(task, algo, run_dir, seed=seed, overrides=dict(overrides),
                             progress=False, **length)
    except Exception as e:  # one failed run is a row saying why, not a lost table
        return {"task": task, "algo": algo, "seed": seed, "error": f"{type(e).__name__}: {e}"}
    final = s["final"]
    return {"task": task, "algo": algo, "seed": seed, "return": final.get("return"),
            "best_return": s["best_return"], "env_steps": final.get("env_steps"),
            "wall_s": time.perf_counter() - t0, "overrides": overrides, "run": str(run_dir)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", nargs="*", default=["dmc/cartpole-swingup", "dmc/pendulum-swingup"],
                   choices=envs.names("dmc"))
    p.add_argument("--algos", nargs="*", default=["ppo", "shac"], choices=ALGOS)
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--budget", type=int, default=1_000_000, help="PPO env steps")
    p.add_argument("--epochs", type=int, default=100, help="shac/hds epochs")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="an override for every run (as twinrl train --set)")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    extra = runner.parse_overrides(args.set)
    rows = [run(t, a, s, args.budget, args.epochs, args.out, extra)
            for t in args.tasks for a in args.algos for s in range(args.seeds)]
    table = []
    for r in rows:
        pub = PUBLISHED.get(r["task"], {})
        fig = pub.get("return")
        table.append([r["task"], r["algo"], r["seed"],
                      "error" if "error" in r else f"{r['return']:.1f}",
                      "" if "error" in r else f"{r.get('env_steps') or float('nan'):.3g}",
                      "" if "error" in r else f"{r['wall_s']:.0f}",
                      "curve only" if fig is None else f"{fig:.0f}",
                      f"{pub.get('steps', float('nan')):.3g}"])
    print_table("Control Suite at a fixed budget (return over 1000 steps, max 1000)",
                ["task", "algo", "seed", "return", "env steps", "wall s", "published PPO",
                 "its steps"], table)
    for r in rows:
        if "error" in r:
            print(f"{r['task']} {r['algo']} seed {r['seed']}: {r['error']}", file=sys.stderr)
    path = write_result(args.out / "dmc.json", {
        "runs": rows, "published": PUBLISHED, "playground_ppo": PLAYGROUND_PPO,
        "cpu_overrides": {"ppo": PPO_CPU, "shac": SHAC_CPU, "hds": HDS_CPU},
        "mean_return": {f"{t}/{a}": float(np.mean([r["return"] for r in rows
                                                     if r["task"] == t and r["algo"] == a
                                                     and "error" not in r] or [np.nan]))
                        for t in args.tasks for a in args.algos}}, args)
    print(f"wrote {path}")
    return 0 if not any("error" in r for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
