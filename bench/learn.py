"""Learn@Sim benchmark: differentiable trainers against model-free and analytic-gradient baselines.

For every task (``pendulum_swingup``, ``cartpole_swingup``; simulated) and algorithm
(``pods``, ``pods2`` = PODS with the second-order step, ``hds``, ``shac``, ``ppo``, ``apg``), over
``--seeds`` seeds:

- final return (deterministic policy, mean over evaluation episodes), mean +- std over seeds;
- wall-clock seconds (warm cache, below) and env steps to first reach 90% of the best final return
  that any algorithm reached on the task (mean over the seeds that reached it, and how many did);
- whether each run **solved** the task (issue #4: an evaluation return >= 130 of the maximum 250
  while the mean of the last 10 evaluations is >= 130 too), and the epoch, seconds and env steps
  at which it first did;
- seconds to reach PPO's final return, and that time as a fraction of PPO's whole run (the issue's
  target for the best differentiable algorithm: <= 1/5), measured twice: on a cold compilation
  cache (compile included: what a first run on a fresh machine waits) and on a warm one
  (learning time: every program loaded from the persistent cache, tracing still included);
- **compile seconds** per algorithm and task, apart from learning: seed 0 runs first with an
  empty JAX compilation cache (``--cache``, emptied at the start), then every seed, seed 0
  included, runs again with the programs in the cache; compile = cold minus warm wall clock of
  seed 0 (the same seed does the same work). The per-seed figures are the warm runs';
- a plot of return against wall-clock and against env steps (``learn.png``), a printed table and
  ``learn.json`` in ``--out``.

Configs are the CLI's (``twinrl.learn.runner.make_config``: class defaults, then
``twinrl.learn.tuned.TUNED[algo][task]``). Algorithms whose module is not there yet (``twinrl.learn.pods``/``hds`` are imported lazily) are
reported as skipped. ``--quick`` runs tiny configurations (a smoke test of this script, numbers
meaningless). The full run takes long on a CPU; run it on an otherwise idle machine::

    python bench/learn.py --out bench/results                    # everything, 3 seeds
    python bench/learn.py --algos shac ppo --envs cartpole_swingup --seeds 1
    python bench/learn.py --quick --out /tmp/learn_quick
    python bench/learn.py --algos shac ppo --envs cartpole_swingup pendulum_swingup push

``--set ALGO.FIELD=VALUE`` overrides one config field for the run (e.g. ``--set shac.epochs=100``),
recorded with the results.

Each finished run is also written to ``--out/learn_runs/TASK-ALGO-SEED.json`` and reused by a
later invocation with the same ``--out`` (``--fresh`` ignores them), so a long benchmark can be
split over several processes (one task each, one core each) or continued after an interruption;
the final invocation with every task then analyses all the runs together.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
import traceback
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, jaxconfig)
import jax
import numpy as np

from twinrl import envs
from twinrl.learn import runner
from twinrl.report import print_table, write_json
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)

ALGOS = ("pods", "pods2", "hds", "shac", "ppo", "apg")
TASKS = ("pendulum_swingup", "cartpole_swingup")
FRACTION = 0.9
SOLVED = 130.0
"""Issue #4's "solved": return >= SOLVED with the SOLVED_WINDOW-evaluation running mean >= it."""
SOLVED_WINDOW = 10

QUICK_TASK = {"episode_length": 40}
QUICK = {
    "shac": dict(epochs=3, num_envs=8, horizon=8, critic_iterations=2, critic_minibatches=2,
                 eval_episodes=2),
    "ppo": dict(num_timesteps=2048, num_envs=8, batch_size=8, num_minibatches=4,
                unroll_length=8, num_updates_per_batch=1, num_evals=3, num_eval_envs=4),
    "apg": dict(policy_updates=4, horizon_length=8, num_envs=4, num_evals=3, num_eval_envs=4),
    # short windows: QUICK_TASK's 40-step episodes are shorter than the default horizon (50)
    "pods": dict(epochs=3, batch_size=4, horizon=8, regression_steps=8, critic_steps=8,
                 eval_episodes=2),
    "hds": dict(epochs=3, batch_size=4, horizon=8, regression_steps=8, critic_steps=8,
                eval_episodes=2),
}


def _override(config, overrides: dict):
    names = {f.name for f in dataclasses.fields(config)}
    return dataclasses.replace(config, **{k: v for k, v in overrides.items() if k in names})


def trainer(algo: str, task: str, quick: bool, overrides: dict | None = None):
    """``(train_fn, config)`` for ``algo`` on ``task``: the CLI's registry and per-task tuned
    configs (``twinrl.learn.runner``), then ``overrides`` (``--set``; ``RunError`` naming a
    field the config lacks); ``ImportError`` if the algorithm's module is absent."""
    _, train, _ = runner.algorithm(algo)
    cfg = runner.make_config(algo, task, overrides)
    if quick:  # the tiny sizes, the user's settings still on top
        cfg = _override(cfg, {**QUICK["pods" if algo == "pods2" else algo], **(overrides or {})})
    return train, cfg


def run(algo: str, task: str, seed: int, quick: bool, overrides: dict | None = None) -> dict:
    train, cfg = trainer(algo, task, quick, overrides)
    env = envs.make(task, **(QUICK_TASK if quick else {}))
    t0 = time.perf_counter()
    last = [t0]

    def progress(epoch, m):
        if time.perf_counter() - last[0] > 15:
            last[0] = time.perf_counter()
            print(f"  {algo} {task} seed {seed}: epoch {epoch} steps {m['env_steps']:.3g} "
                  f"return {m['return']:.1f} ({m['wall_s']:.0f} s)", flush=True)

    _, _, metrics = train(env, cfg, jax.random.PRNGKey(seed), progress_fn=progress)
    cfg_json = cfg.to_dict() if hasattr(cfg, "to_dict") else dataclasses.asdict(cfg)
    return {"seed": seed, "config": cfg_json, "wall_s": metrics["wall_s"],
            "env_steps": metrics["env_steps"], "return": metrics["return"],
            "total_s": time.perf_counter() - t0}


def parse_sets(items: list[str]) -> dict[str, dict]:
    """``["shac.epochs=100", ...]`` -> ``{"shac": {"epochs": 100}}`` (values as
    ``runner.parse_overrides`` reads them); ``ValueError`` naming a malformed item."""
    out: dict[str, dict] = {}
    for key, value in runner.parse_overrides(items).items():
        algo, dot, field = key.partition(".")
        if not (dot and algo and field):
            raise ValueError(f"--set {key!r}: expected ALGO.FIELD=VALUE")
        out.setdefault(algo, {})[field] = tuple(value) if isinstance(value, list) else value
    return out


def first_reach(run_: dict, threshold: float) -> tuple[float, float]:
    """(wall_s, env_steps) of the first evaluation at or above ``threshold``; NaN if none."""
    r = np.asarray(run_["return"], float)
    hit = np.flatnonzero(np.nan_to_num(r, nan=-np.inf) >= threshold)
    if not hit.size:
        return float("nan"), float("nan")
    return float(run_["wall_s"][hit[0]]), float(run_["env_steps"][hit[0]])


def first_solved(run_: dict) -> tuple[float, float, float]:
    """(epoch, wall_s, env_steps) of the first evaluation that solves the task (``SOLVED``);
    NaN if none."""
    r = np.nan_to_num(np.asarray(run_["return"], float), nan=-np.inf)
    for i in range(SOLVED_WINDOW - 1, len(r)):
        if r[i] >= SOLVED and r[i - SOLVED_WINDOW + 1:i + 1].mean() >= SOLVED:
            return float(i + 1), float(run_["wall_s"][i]), float(run_["env_steps"][i])
    return float("nan"), float("nan"), float("nan")


def _mean(xs) -> float:
    xs = [x for x in xs if np.isfinite(x)]
    return float(np.mean(xs)) if xs else float("nan")


def analyse(task_runs: dict[str, list[dict]], cold: dict[str, dict] | None = None) -> dict:
    finals = {a: [r["return"][-1] for r in runs] for a, runs in task_runs.items() if runs}
    best = max(np.mean(f) for f in finals.values())
    threshold = FRACTION * best
    ppo_final = np.mean(finals["ppo"]) if "ppo" in finals else float("nan")
    ppo_wall = (np.mean([r["wall_s"][-1] for r in task_runs["ppo"]]) if "ppo" in finals
                else float("nan"))
    cold = cold or {}
    ppo_cold = cold.get("ppo")
    ppo_cold_wall = ppo_cold["wall_s"][-1] if ppo_cold else float("nan")
    out = {"best_final_return": best, "threshold": threshold, "ppo_final_return": ppo_final,
           "ppo_wall_s": ppo_wall, "ppo_cold_wall_s": ppo_cold_wall, "algos": {}}
    for a, runs in task_runs.items():
        if not runs:
            continue
        c = cold.get(a)
        compile_s = c["wall_s"][-1] - runs[0]["wall_s"][-1] if c else float("nan")
        cold_to_ppo = first_reach(c, ppo_final)[0] if c and np.isfinite(ppo_final) else float("nan")
        reach = [first_reach(r, threshold) for r in runs]
        solved = [first_solved(r) for r in runs]
        to_ppo = [first_reach(r, ppo_final)[0] for r in runs] if np.isfinite(ppo_final) else []
        out["algos"][a] = {
            "final_mean": float(np.mean(finals[a])), "final_std": float(np.std(finals[a])),
            "wall_s_mean": float(np.mean([r["wall_s"][-1] for r in runs])),
            "env_steps_final": float(np.mean([r["env_steps"][-1] for r in runs])),
            "time_to_threshold_s": _mean([t for t, _ in reach]),
            "steps_to_threshold": _mean([s for _, s in reach]),
            "reached": int(sum(np.isfinite(t) for t, _ in reach)), "seeds": len(runs),
            "best_mean": float(np.mean([np.max(r["return"]) for r in runs])),
            "solved": int(sum(np.isfinite(e) for e, _, _ in solved)),
            "epochs_to_solved": _mean([e for e, _, _ in solved]),
            "time_to_solved_s": _mean([t for _, t, _ in solved]),
            "steps_to_solved": _mean([x for _, _, x in solved]),
            "time_to_ppo_final_s": _mean(to_ppo),
            "fraction_of_ppo_wall": _mean(to_ppo) / ppo_wall if to_ppo else float("nan"),
            "ppo_final_reached": int(sum(np.isfinite(t) for t in to_ppo)),
            "fraction_of_ppo_wall_per_seed": [t / ppo_wall for t in to_ppo],
            "compile_s": compile_s,
            "cold_wall_s": c["wall_s"][-1] if c else float("nan"),
            "cold_time_to_ppo_final_s": cold_to_ppo,
            "cold_fraction_of_ppo_cold_wall": cold_to_ppo / ppo_cold_wall,
            "runs": runs,
            "cold_run": c,
        }
    return out


def plot(results: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(results)
    fig, axes = plt.subplots(len(tasks), 2, figsize=(11, 3.6 * len(tasks)), squeeze=False)
    colours = dict(zip(ALGOS, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    for row, task in zip(axes, tasks):
        res = results[task]
        for a, r in res["algos"].items():
            for i, run_ in enumerate(r["runs"]):
                kw = dict(color=colours.get(a), alpha=0.8, lw=1.2, label=a if i == 0 else None)
                row[0].plot(run_["wall_s"], run_["return"], **kw)
                row[1].plot(run_["env_steps"], run_["return"], **kw)
        for ax, xl in zip(row, ("wall-clock (s, programs from the compilation cache)", "env steps")):
            ax.axhline(res["threshold"], color="grey", ls=":", lw=1,
                       label=f"{FRACTION:.0%} of best final")
            ax.set_xlabel(xl)
            ax.set_ylabel("return")
            ax.set_title(task)
            ax.grid(alpha=0.3)
        row[1].set_xscale("log")
        row[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=3, help="seeds per algorithm and task")
    p.add_argument("--algos", nargs="*", default=list(ALGOS), choices=ALGOS)
    p.add_argument("--envs", nargs="*", default=list(TASKS), choices=envs.names())
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    p.add_argument("--quick", action="store_true", help="tiny configurations (smoke test)")
    p.add_argument("--fresh", action="store_true",
                   help="re-run every run instead of reusing --out/learn_runs/*.json")
    p.add_argument("--cache", type=Path, default=None,
                   help="JAX compilation cache of the runs (default --out/jax_cache); emptied "
                        "at the start, so each algorithm's first run compiles cold")
    p.add_argument("--set", action="append", default=[], metavar="ALGO.FIELD=VALUE",
                   help="override a config field of one algorithm (repeatable)")
    args = p.parse_args(argv)
    if args.seeds < 1:
        p.error(f"--seeds must be >= 1, got {args.seeds}")
    try:
        overrides = parse_sets(args.set)
        for algo in overrides:  # a field the config lacks, before any run
            if algo in args.algos:
                for task in args.envs:
                    trainer(algo, task, args.quick, overrides[algo])
    except (ValueError, runner.RunError) as e:
        p.error(str(e))
    runs_dir = args.out / "learn_runs"
    cache = args.cache or args.out / "jax_cache"
    shutil.rmtree(cache, ignore_errors=True)
    cache.mkdir(parents=True)
    jax.config.update("jax_compilation_cache_dir", str(cache))  # before the first compile

    def saved(algo, task, tag):
        cached = runs_dir / f"{task}-{algo}-{tag}.json"
        if not cached.exists() or args.fresh:
            return None
        data = json.loads(cached.read_text())
        same = json.loads(json.dumps(overrides.get(algo)))
        return data["run"] if data.get("quick") == args.quick and data.get("overrides") == same \
            else None

    def all_runs(algo, task):
        """Seed 0 on a cold cache (for the compile time), then every seed on a warm one; runs
        saved by an earlier invocation are reused only all together (else the warm runs would
        compile cold)."""
        tags = ["cold"] + [str(s) for s in range(args.seeds)]
        old = [saved(algo, task, t) for t in tags]
        if all(r is not None for r in old):
            print(f"{algo} on {task}: reusing {runs_dir}/{task}-{algo}-*.json", flush=True)
            return old[0], old[1:]
        out = []
        for tag in tags:
            seed = 0 if tag == "cold" else int(tag)
            print(f"{algo} on {task}, {'seed 0, cold cache' if tag == 'cold' else 'seed ' + tag} "
                  "...", flush=True)
            out.append(run(algo, task, seed, args.quick, overrides.get(algo)))
            write_json(runs_dir / f"{task}-{algo}-{tag}.json",
                       {"quick": args.quick, "overrides": overrides.get(algo), "run": out[-1]})
        return out[0], out[1:]

    results, skipped = {}, {}
    for task in args.envs:
        task_runs, cold = {}, {}
        for algo in args.algos:
            try:
                trainer(algo, task, args.quick)
            except ImportError as e:
                skipped[algo] = f"not available: {e}"
                continue
            runs = []
            try:
                cold[algo], runs = all_runs(algo, task)
            except Exception as e:  # one broken algorithm must not sink the others' numbers
                traceback.print_exc()
                skipped[f"{algo}/{task}"] = f"failed: {type(e).__name__}: {e}"
            task_runs[algo] = runs
        if any(task_runs.values()):
            results[task] = analyse({a: r for a, r in task_runs.items() if r}, cold)

    rows = []
    for task, res in results.items():
        for a, r in res["algos"].items():
            rows.append([task, a, f"{r['final_mean']:.1f} ± {r['final_std']:.1f}",
                         r["wall_s_mean"], r["env_steps_final"], r["time_to_threshold_s"],
                         r["steps_to_threshold"], f"{r['reached']}/{r['seeds']}",
                         f"{r['solved']}/{r['seeds']}", r["time_to_solved_s"],
                         r["time_to_ppo_final_s"], r["fraction_of_ppo_wall"],
                         f"{r['ppo_final_reached']}/{r['seeds']}", r["compile_s"],
                         r["cold_fraction_of_ppo_cold_wall"]])
    print_table(f"Learn@Sim ({args.seeds} seeds; threshold = {FRACTION:.0%} of the best final "
                f"return per task; {jax.devices()[0].platform})",
                ["task", "algo", "final return", "wall s", "env steps", "s to thr",
                 "steps to thr", "reached", "solved", "s to solved", "s to PPO final",
                 "/ PPO wall", "reached PPO", "compile s", "cold / PPO cold"], rows)
    for k, v in skipped.items():
        print(f"skipped {k}: {v}")
    args.out.mkdir(parents=True, exist_ok=True)
    if results:
        plot(results, args.out / "learn.png")
    meta = {"fraction": FRACTION, "devices": len(jax.devices())}
    path = write_result(args.out / "learn.json", {"meta": meta, "skipped": skipped,
                                                  "tasks": results}, args)
    print(f"wrote {path} and {args.out / 'learn.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
