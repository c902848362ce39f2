"""Learning on the DeepMind Control Suite tasks (``dmc/``) at a fixed budget, beside published
Control Suite figures.

For every task and algorithm (Brax PPO, ``ppo``; twinrl's first-order learners ``shac`` and
``hds``), over ``--seeds`` seeds, one ``twinrl.learn.runner.train_run`` with the CLI's configs
(``make_config``: class defaults, ``tuned.TUNED``, then this bench's ``--set`` and budget): the
final return (deterministic policy, over the evaluation episodes; a Control Suite episode is
1000 steps with per-step reward in [0, 1], so returns are in [0, 1000]), the env steps and the
wall clock.

Published figures (``PUBLISHED``, written into ``dmc.json``'s ``published`` block): the
learning-curve data TD-MPC2 (Hansen, Su and Wang, ICLR 2024) released with its paper, for SAC,
DreamerV3 and TD-MPC2 on the suite's tasks from states, 3 seeds each (``TDMPC2_CURVES``). Its
DMControl wrapper repeats each action twice and cuts episodes at 500 agent steps, so one of its
logged steps is two of the suite's control steps (ours) and its episode return is on the same
0-1000 scale. Each figure is the mean (and sample sd) over seeds of the evaluation return logged
at that step, read from the CSV at the commit given. MuJoCo Playground's Brax PPO runs (60 M
steps, 2048 environments, on a GPU) are recorded with their settings but no return: the paper
shows them as learning curves only. ``--budget`` steps on a 2-core CPU lies one to two orders of
magnitude below Playground's budget and level with TD-MPC2's 1 M agent steps (2 M control
steps), though equal steps are not equal computation: those methods are off-policy and reuse
each step in many updates (DreamerV3 and TD-MPC2 also learn a world model, TD-MPC2 plans).

    python bench/dmc.py --out bench/results                       # every task, ppo+shac, 1 seed
    python bench/dmc.py --tasks dmc/cartpole-swingup --algos ppo --budget 200000 --out /tmp/dmc
    python bench/dmc.py --published-only --out bench/results      # rewrite only ``published``

Writes ``dmc.json`` (``bench/benchio.py``'s ``meta`` + one row per run + the settings) and
prints the table; each run's own directory (metrics.csv, curve.png, policy) is under
``--out/dmc_runs/``. ``--published-only`` trains nothing: it rewrites the ``published`` block of
an existing ``OUT/dmc.json``, keeping its runs and their ``meta``, and records when and by which
command and commit the block was written (``meta.published_written``).
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

TDMPC2 = "https://github.com/nicklashansen/tdmpc2"
TDMPC2_COMMIT = "e9f59321933cbc8e11a002b842adc7d4ffae8ff1"
TDMPC2_PAPER = "https://arxiv.org/abs/2310.16828"
TDMPC2_WRAPPER = f"{TDMPC2}/blob/{TDMPC2_COMMIT}/tdmpc2/envs/dmcontrol.py"
"""Where its steps are defined: ``DMControlWrapper.step`` repeats each action twice (summing the
rewards), ``Timeout(env, max_episode_steps=500)`` ends an episode."""
TDMPC2_ACTION_REPEAT = 2
TDMPC2_ALGOS = {"sac": "SAC", "tdmpc2": "TD-MPC2", "dreamerv3": "DreamerV3"}
TDMPC2_CURVES: dict[str, dict[str, dict[int, tuple[float, float, int]]]] = {
    # results/<algo>/<task>.csv (step, reward, seed): {agent step: (mean, sample sd, seeds)}
    "sac": {
        "cartpole-swingup": {100_000: (835.0, 9.5, 3), 500_000: (834.6, 23.1, 3),
                             1_000_000: (838.7, 13.3, 3)},
        "cartpole-balance": {100_000: (998.7, 0.6, 3), 500_000: (984.1, 12.6, 3),
                             1_000_000: (998.1, 2.0, 3)},
        "pendulum-swingup": {100_000: (96.0, 94.1, 3), 500_000: (408.4, 369.0, 3),
                             1_000_000: (353.6, 450.5, 3)},
        "reacher-easy": {100_000: (540.4, 410.4, 3), 500_000: (918.3, 61.6, 3),
                         1_000_000: (913.9, 112.9, 3)},
        "finger-spin": {100_000: (762.4, 16.5, 3), 500_000: (872.8, 76.0, 3),
                        1_000_000: (878.1, 66.3, 3)},
        "cheetah-run": {100_000: (310.1, 65.3, 3), 500_000: (594.5, 173.0, 3),
                        1_000_000: (730.1, 3.2, 3)},
        "walker-walk": {100_000: (708.2, 204.3, 3), 500_000: (952.9, 4.6, 3),
                        1_000_000: (957.3, 3.6, 3)},
    },
    "tdmpc2": {
        "cartpole-swingup": {100_000: (839.4, 43.1, 3), 500_000: (876.1, 8.8, 3),
                             1_000_000: (875.9, 9.7, 3)},
        "cartpole-balance": {100_000: (997.8, 0.7, 3), 500_000: (993.9, 6.5, 3),
                             1_000_000: (974.7, 40.5, 3)},
        "pendulum-swingup": {100_000: (724.0, 146.9, 3), 500_000: (841.7, 37.4, 3),
                             1_000_000: (819.4, 46.6, 3)},
        "reacher-easy": {100_000: (936.9, 66.7, 3), 500_000: (919.4, 57.4, 3),
                         1_000_000: (982.7, 4.8, 3)},
        "finger-spin": {100_000: (947.5, 34.2, 3), 500_000: (984.6, 3.9, 3),
                        1_000_000: (985.7, 1.1, 3)},
        "cheetah-run": {100_000: (519.1, 83.8, 3), 500_000: (757.6, 142.9, 3),
                        1_000_000: (844.4, 103.3, 3)},
        "walker-walk": {100_000: (961.9, 12.5, 3), 500_000: (978.7, 4.9, 3),
                        1_000_000: (979.7, 4.2, 3)},
    },
    "dreamerv3": {
        "cartpole-swingup": {100_000: (676.7, 40.8, 3), 500_000: (788.8, 20.3, 3),
                             1_000_000: (780.0, 21.2, 3)},
        "cartpole-balance": {100_000: (912.6, 63.2, 3), 500_000: (955.2, 12.6, 3),
                             1_000_000: (952.5, 6.4, 3)},
        "pendulum-swingup": {100_000: (699.3, 209.9, 3), 500_000: (739.9, 36.8, 3),
                             1_000_000: (810.3, 44.8, 3)},
        "reacher-easy": {100_000: (872.1, 46.4, 3), 500_000: (940.1, 0.7, 2),
                         1_000_000: (914.6, 44.4, 3)},
        "finger-spin": {100_000: (328.3, 58.6, 3), 500_000: (751.5, 64.2, 3),
                        1_000_000: (758.0, 62.9, 3)},
        "cheetah-run": {100_000: (335.7, 63.0, 3), 500_000: (493.8, 40.9, 3),
                        1_000_000: (638.2, 6.4, 3)},
        "walker-walk": {100_000: (630.1, 53.3, 3), 500_000: (878.4, 29.1, 3),
                        1_000_000: (820.6, 49.3, 3)},
    },
}
"""TD-MPC2's released evaluation returns (``TDMPC2`` at ``TDMPC2_COMMIT``, ``results/<algo>/
<task>.csv``; the pixel runs are a separate folder, ``results/tdmpc2-pixels``, so these are from
states): per algorithm and task, at 100 k, 500 k and 1 M logged agent steps (x
``TDMPC2_ACTION_REPEAT`` control steps), the mean, the sample sd over seeds and the number of
seeds logged there. Computed from the CSVs, not read off a plot."""

TASK_NAMES = ("dmc/cartpole-swingup", "dmc/cartpole-balance", "dmc/pendulum-swingup",
              "dmc/reacher-easy", "dmc/finger-spin", "dmc/cheetah-run", "dmc/walker-walk")


def published(task: str) -> list[dict]:
    """The published figures for ``task``: TD-MPC2's SAC, TD-MPC2 and DreamerV3 (states, at 1 M
    agent steps = 2 M control steps, with the whole curve subset in ``curve``, keyed by control
    steps) and MuJoCo Playground's Brax PPO (``return`` None, with the reason)."""
    short = task.split("/", 1)[1]
    out = []
    for algo, name in TDMPC2_ALGOS.items():
        curve = TDMPC2_CURVES[algo].get(short)
        if curve is None:
            out.append({"algo": name, "return": None, "reason": "no CSV for this task"})
            continue
        agent = max(curve)
        mean, sd, seeds = curve[agent]
        out.append({
            "algo": name, "obs": "states", "return": mean, "sd": sd, "seeds": seeds,
            "agent_steps": agent, "steps": agent * TDMPC2_ACTION_REPEAT,
            "curve": {str(k * TDMPC2_ACTION_REPEAT): list(v) for k, v in sorted(curve.items())},
            "source": f"{TDMPC2}/blob/{TDMPC2_COMMIT}/results/{algo}/{short}.csv",
            "reference": f"TD-MPC2 (Hansen, Su, Wang, ICLR 2024), {TDMPC2_PAPER}: the "
                         "learning-curve data released with the paper (its DMControl figures)",
            "settings": TDMPC2_WRAPPER,
            "note": "mean and sample sd over seeds of the evaluation return logged at that "
                    "agent step; an agent step is two control steps (action repeat 2)"})
    out.append({"algo": "Brax PPO (MuJoCo Playground)", "obs": "states", "return": None,
                "steps": PLAYGROUND_PPO["num_timesteps"], "source": PAPER,
                "settings": PLAYGROUND,
                "reason": "the paper gives its Control Suite results as learning curves only "
                          "(a figure, no table or data file): no number is read off a plot"})
    return out


PUBLISHED: dict[str, list[dict]] = {name: published(name) for name in TASK_NAMES}
"""The published figures per registered ``dmc/`` task (``published``)."""

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


def nearest_published(task: str, steps: float | None) -> dict[str, tuple | None]:
    """Per published algorithm with a curve, its ``(control steps, mean, sd, seeds)`` at the
    logged point nearest ``steps`` control steps (None without a curve or ``steps``)."""
    out = {}
    for fig in PUBLISHED.get(task, []):
        curve = fig.get("curve")
        if not curve or steps is None:
            continue
        k = min(curve, key=lambda c: abs(int(c) - steps))
        out[fig["algo"]] = (int(k), *curve[k])
    return out


def write_published(path: Path, args) -> Path:
    """Rewrite only the ``published`` block of the result at ``path`` (its runs, settings and
    ``meta`` kept); ``meta.published_written`` records this command, commit and date."""
    from benchio import metadata

    if not path.exists():
        raise SystemExit(f"--published-only: {path} does not exist (run the bench first)")
    doc = json.loads(path.read_text())
    doc["published"] = PUBLISHED
    m = metadata(args)
    doc.setdefault("meta", {})["published_written"] = {
        k: m[k] for k in ("command", "commit", "dirty", "date") if k in m}
    from twinrl.report import write_json

    return write_json(path, doc)


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
    p.add_argument("--published-only", action="store_true",
                   help="train nothing: rewrite the published block of OUT/dmc.json, keeping "
                        "its runs and meta")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if args.published_only:
        print(f"wrote {write_published(args.out / 'dmc.json', args)}")
        return 0
    extra = runner.parse_overrides(args.set)
    rows = [run(t, a, s, args.budget, args.epochs, args.out, extra)
            for t in args.tasks for a in args.algos for s in range(args.seeds)]
    table = []
    for r in rows:
        near = nearest_published(r["task"], r.get("env_steps"))
        table.append([r["task"], r["algo"], r["seed"],
                      "error" if "error" in r else f"{r['return']:.1f}",
                      "" if "error" in r else f"{r.get('env_steps') or float('nan'):.3g}",
                      "" if "error" in r else f"{r['wall_s']:.0f}",
                      " / ".join(f"{a} {v[1]:.0f}" for a, v in near.items()) or "-",
                      f"{next(iter(near.values()))[0]:.3g}" if near else "-"])
    print_table("Control Suite at a fixed budget (return over 1000 steps, max 1000)",
                ["task", "algo", "seed", "return", "env steps", "wall s",
                 "published (TD-MPC2's data, states)", "their steps"], table)
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
