"""Benchmark: real-twin steps model-free SAC and TD3 (sbx-rl) need to reach 90 % of the oracle.

Our loop (``twinrl run``) learns in the identified simulator and spends only a few real-twin steps
(1,000 in ``runs/main``). This asks what a model-free learner trained *directly on the real twin*
(the loop run's own: a ``twinrl.real.remote.TwinClient`` with the run's ``eval/twin.json``)
spends to get as far. For each task, algorithm
(sbx-rl ``SAC`` and ``TD3``, JAX implementations of the Stable-Baselines3 algorithms) and seed:

- train on the real twin; every ``--eval-every`` real steps (default 500) score the
  deterministic policy with ``twinrl.eval.policy_real_return`` on ``--eval-episodes`` (default 3)
  fresh episodes: a fresh twin with the same hidden perturbation and the loop's fixed start states,
  so scores compare with the loop's. Evaluation steps are not counted;
- stop when the score reaches 90 % of the oracle return (a policy trained in a simulator with the
  twin's true parameters), or at ``--max-steps`` real steps. TD3 runs first; SAC then stops at the
  step count TD3 reached the target in (only the better of the two enters the ratio; ``--no-cap``
  trains both fully).

The loop is counted the same way (``loop_steps_to_target``): its score is the deployed policy's
return on those same evaluation episodes (``adapted_real_return``), and its count the real steps
recorded before that policy was made (``data steps``); the count that also includes the round's
own recorded deployment episodes is reported beside it, with its ratio.

Hyper-parameters: sbx defaults (MLP 256x256, lr 3e-4, batch 256, gamma 0.99, tau 0.005, one
gradient step per env step, buffer 1e6) except ``learning_starts=1000`` (uniform random actions
first, for both) and, for TD3, Gaussian exploration noise with sd 0.1 (SB3/sbx TD3 has no
exploration noise by default; 0.1 is the RL-Zoo value).

The oracle return and the loop's numbers come from a loop run's ``summary.json``
(``--loop-summary``, one per task/seed; keys ``rounds[0].oracle_return``, ``final.real_steps``,
``final.real_return``, ``final.sim_policy_real_return``). Reported per task/seed: real steps to
90 % of the oracle per algorithm (``> max`` when not reached), wall seconds, the return at each
evaluation, and the ratio (steps of the better of SAC and TD3) / (loop steps), for both loop counts
-- a lower bound ``>= max/loop`` when neither model-free run got there, none when the loop did
not; plus the loop's own rows and the sim-only policy without adaptation
(``sim_policy_real_return``, made from round 0's real steps). Writes
``bench/results/sim2real.json`` (after every run) and ``bench/results/sim2real.png`` (return vs
real steps). Each finished model-free run is
also kept in ``sim2real_runs/TASK-ALGO-SEED.json`` beside ``--out`` and reused by a later
invocation asking the same question (``--fresh`` re-runs), so tasks and seeds can be run in
separate processes and then tabulated together.

Needs the ``bench`` extra (sbx-rl, stable-baselines3, CPU torch):
``pip install -e '.[bench]'`` in a separate environment (it must keep jax 0.9.2).
Run: ``python bench/sim2real.py --tasks cartpole_swingup --seeds 0 --max-steps 25000
--loop-summary runs/main/summary.json``
(25,000 steps: SAC ~6.5 min, TD3 ~4 min on 2 CPU cores).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import twinrl  # noqa: F401  (compilation cache)
from twinrl import envs, report
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)
from twinrl.eval import policy_real_return

RESULTS = Path(__file__).resolve().parent / "results"
FRACTION = 0.9
LEARNING_STARTS = 1000
TD3_NOISE_SD = 0.1


def import_sbx():
    """sbx (and through it stable-baselines3 and torch) is an optional dependency of the bench."""
    try:
        import sbx
        from stable_baselines3.common.callbacks import BaseCallback
        from stable_baselines3.common.noise import NormalActionNoise
    except ImportError as e:
        raise SystemExit(f"bench/sim2real.py needs sbx-rl, stable-baselines3 and torch ({e}); "
                         "install the `bench` extra's pinned versions with --no-deps in a copy "
                         "of the venv, so the jax pins hold (pyproject.toml, README)") from None
    return sbx, BaseCallback, NormalActionNoise


def load_summary(path: Path) -> dict:
    """The loop numbers this benchmark compares with; a clear error when any is missing."""
    if not path.exists():
        raise SystemExit(f"loop summary {path} not found (run `twinrl run` first, or pass "
                         "--loop-summary PATH)")
    s = json.loads(path.read_text())
    try:
        out = {"task": s["env"], "seed": int(s["seed"]),
               "oracle_return": s["rounds"][0]["oracle_return"],
               "loop_real_steps": s["final"]["real_steps"],
               "loop_real_return": s["final"]["real_return"],
               "sim_policy_real_return": s["final"]["sim_policy_real_return"],
               "rounds": [{k: r.get(k) for k in ("round", "real_steps", "real_return",
                                                 "sim_policy_real_return",
                                                 "adapted_real_return")}
                          for r in s["rounds"]]}
    except (KeyError, IndexError, TypeError) as e:
        raise SystemExit(f"{path} lacks {e} (needs env, seed, rounds[0].oracle_return, "
                         "final.real_steps, final.real_return, final.sim_policy_real_return)")
    missing = [k for k, v in out.items() if v is None]
    if missing:
        raise SystemExit(f"{path}: {', '.join(missing)} is null (was the loop run with the "
                         "oracle on?)")
    out["path"] = str(path)
    # The loop's twin: seeded by the run's secret salt (twinrl.real.remote), which the run keeps
    # in eval/ beside its summary; a run from before the salt used the public-seed twin.
    secret = path.parent / "eval" / "twin.json"
    out["secret"] = str(secret) if secret.exists() else None
    return out


def loop_steps_to_target(loop: dict, target: float) -> dict:
    """Real steps the loop spent to reach ``target``, counted the way the model-free runs are.

    A model-free run's count is its training steps when an evaluation (unrecorded, uncounted
    episodes from the fixed start states of ``policy_real_return``) first scores >= target. The
    loop's like-for-like score is a round's ``adapted_real_return``: the policy it deploys, on
    those same evaluation episodes. That policy was made from the real steps recorded *before*
    the round's deployment (the previous round's ``real_steps``): ``data_steps``. The round's own
    deployment episodes, recorded and counted by the loop, are included in ``all_steps`` (the
    conservative count). ``round`` None: no round reached it (both counts are then the loop's
    total, lower bounds)."""
    rounds = loop["rounds"]
    for prev, r in zip(rounds, rounds[1:]):
        score = r.get("adapted_real_return")
        if score is not None and score >= target:
            return {"round": r["round"], "score": score, "data_steps": prev["real_steps"],
                    "all_steps": r["real_steps"]}
    return {"round": None, "score": None, "data_steps": loop["loop_real_steps"],
            "all_steps": loop["loop_real_steps"]}


def train(algo: str, task: str, seed: int, target: float, max_steps: int, eval_every: int,
          eval_episodes: int, secret: str | None = None) -> dict:
    from twinrl.real.remote import TwinClient

    sbx, BaseCallback, NormalActionNoise = import_sbx()
    twin = TwinClient(task, seed=seed, secret=secret)  # the loop's twin, in its own process
    if algo == "sac":
        model = sbx.SAC("MlpPolicy", twin, learning_starts=LEARNING_STARTS, seed=seed)
    else:
        nu = twin.action_space.shape[0]
        model = sbx.TD3("MlpPolicy", twin, learning_starts=LEARNING_STARTS, seed=seed,
                        action_noise=NormalActionNoise(np.zeros(nu), TD3_NOISE_SD * np.ones(nu)))
    act = lambda obs: model.predict(obs, deterministic=True)[0]  # noqa: E731
    curve: list[dict] = []
    t0 = time.perf_counter()
    eval_s = [0.0]

    def evaluate(steps: int) -> bool:
        t = time.perf_counter()
        ret = policy_real_return(task, seed, act, eval_episodes, None, secret)
        eval_s[0] += time.perf_counter() - t
        curve.append({"real_steps": steps, "return": ret, "wall_s": time.perf_counter() - t0})
        print(f"  {task} {algo} seed {seed}: {steps:>6} real steps  return {ret:8.2f}"
              f"  (target {target:.2f})  {time.perf_counter() - t0:6.0f} s", flush=True)
        return ret >= target

    class Eval(BaseCallback):
        def _on_step(self) -> bool:
            n = self.num_timesteps
            if n % eval_every == 0 or n >= max_steps:
                return not evaluate(n)  # False stops learn()
            return True

    model.learn(total_timesteps=max_steps, callback=Eval())
    twin.close()
    reached = next((c["real_steps"] for c in curve if c["return"] >= target), None)
    wall = time.perf_counter() - t0
    return {"task": task, "seed": seed, "algo": algo, "target": target, "max_steps": max_steps,
            "eval_every": eval_every, "eval_episodes": eval_episodes, "twin_secret": secret,
            "steps_to_target": reached, "real_steps_trained": int(model.num_timesteps),
            "final_return": curve[-1]["return"] if curve else None,
            "best_return": max(c["return"] for c in curve) if curve else None,
            "wall_s": wall, "eval_wall_s": eval_s[0], "curve": curve,
            "hyperparameters": {"learning_starts": LEARNING_STARTS,
                                **({"action_noise_sd": TD3_NOISE_SD} if algo == "td3" else {}),
                                "other": "sbx defaults"}}


def ratio(runs: list[dict], loop_steps: int) -> dict:
    """(real steps of the better model-free run) / ``loop_steps``; a lower bound when neither
    reached the target (then the most steps any of them trained)."""
    reached = [r["steps_to_target"] for r in runs if r["steps_to_target"] is not None]
    if reached:
        return {"value": min(reached) / loop_steps, "lower_bound": False}
    return {"value": max(r["real_steps_trained"] for r in runs) / loop_steps, "lower_bound": True}


def fmt_ratio(r: dict | None) -> str:
    if r is None:
        return "none (the loop did not reach the target)"
    return (">= " if r["lower_bound"] else "") + f"{r['value']:.3g}"


def _same_twin(a: str | None, b: str | None) -> bool:
    """Whether two loop runs' twin secrets (``OUT/eval/twin.json`` paths) name the same twin: equal
    paths, or files with the same content (two runs of one task and seed meet the same salted
    twin, so a model-free run made against one serves the other)."""
    if a == b:
        return True
    if a is None or b is None or not (Path(a).exists() and Path(b).exists()):
        return False
    return json.loads(Path(a).read_text()) == json.loads(Path(b).read_text())


def cached_run(path: Path, target: float, max_steps: int, eval_every: int,
               eval_episodes: int, secret: str | None = None) -> dict | None:
    """A finished run from an earlier invocation, scored against this invocation's ``target``
    from its evaluation curve when the curve answers the question (same evaluation episodes):

    - an evaluation within ``max_steps`` scored >= ``target``: the first such step, if the run
      evaluated every ``eval_every`` steps (else a finer interval might have found an earlier one);
    - none did, and the run trained ``max_steps`` or more without stopping at a target of its own:
      not reached (a lower bound, whatever its evaluation interval).

    A run that stopped early at its own lower target says nothing about a higher one: None."""
    if not path.exists():
        return None
    r = json.loads(path.read_text())
    if r.get("eval_episodes") != eval_episodes or not _same_twin(r.get("twin_secret"), secret):
        return None  # other evaluation episodes, or another twin
    rescored = {"target": target, "rescored_from_target": r["target"]}
    hit = next((c["real_steps"] for c in r.get("curve", []) if c["return"] >= target), None)
    if hit is not None:
        ok = r.get("eval_every") == eval_every and hit <= max_steps
        return {**r, **rescored, "steps_to_target": hit} if ok else None
    if r["steps_to_target"] is not None or r["real_steps_trained"] < max_steps:
        return None
    return {**r, **rescored, "steps_to_target": None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", nargs="+", default=["cartpole_swingup"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--algos", nargs="+", choices=["sac", "td3"], default=["td3", "sac"],
                    help="run in this order; each later one stops at the fewest steps an "
                         "earlier one reached the target in (only the better one counts) "
                         "unless --no-cap")
    ap.add_argument("--no-cap", action="store_true",
                    help="train every algorithm to --max-steps or its target")
    ap.add_argument("--fresh", action="store_true",
                    help="ignore the runs kept from earlier invocations (--out stem + _runs/)")
    ap.add_argument("--max-steps", type=int, default=25_000,
                    help="real-twin steps per run, at most")
    ap.add_argument("--eval-every", type=int, default=500, help="real steps between evaluations")
    ap.add_argument("--eval-episodes", type=int, default=3)
    ap.add_argument("--loop-summary", nargs="+", type=Path,
                    default=[Path("runs/main/summary.json")],
                    help="summary.json of loop runs, one per task/seed benchmarked")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--plot", type=Path, default=None, help="default: OUT/sim2real.png")
    args = ap.parse_args(argv)
    import_sbx()  # fail fast, before any training, when the extra is missing

    loops = {}
    for p in args.loop_summary:
        s = load_summary(p)
        loops[(s["task"], s["seed"])] = s
    for task in args.tasks:
        for seed in args.seeds:
            if (task, seed) not in loops:
                raise SystemExit(f"no --loop-summary for {task} seed {seed} "
                                 f"(have: {sorted(loops)})")

    runs_dir = args.out / "sim2real_runs"
    runs: list[dict] = []
    comparisons: list[dict] = []
    out = {"fraction_of_oracle": FRACTION, "max_steps": args.max_steps,
           "eval_every": args.eval_every, "eval_episodes": args.eval_episodes,
           "runs": runs, "comparisons": comparisons}
    for task in args.tasks:
        for seed in args.seeds:
            loop = loops[(task, seed)]
            target = FRACTION * loop["oracle_return"]
            these = []
            for algo in args.algos:
                cap = args.max_steps
                reached = [r["steps_to_target"] for r in these if r["steps_to_target"]]
                if reached and not args.no_cap:
                    cap = min(cap, min(reached))
                path = runs_dir / f"{task}-{algo}-{seed}.json"
                r = None if args.fresh else cached_run(path, target, cap, args.eval_every,
                                                       args.eval_episodes, loop["secret"])
                if r is None:
                    r = train(algo, task, seed, target, cap, args.eval_every,
                              args.eval_episodes, loop["secret"])
                    report.write_json(path, r)
                else:
                    print(f"  {task} {algo} seed {seed}: kept from {path}")
                these.append(r)
                runs.append(r)
                write_result(args.out / "sim2real.json", out, args)  # durable after every run
            loop_reach = loop_steps_to_target(loop, target)
            loop_reached = loop_reach["round"] is not None  # else both counts are lower bounds
            comparisons.append({**loop, "target": target, "loop_reach": loop_reach,
                                "ratio_best_to_loop": (ratio(these, loop_reach["data_steps"])
                                                       if loop_reached else None),
                                "ratio_best_to_loop_all_steps": (
                                    ratio(these, loop_reach["all_steps"])
                                    if loop_reached else None)})
            write_result(args.out / "sim2real.json", out, args)

    rows = []
    for c in comparisons:
        task, seed = c["task"], c["seed"]
        for r in (r for r in runs if (r["task"], r["seed"]) == (task, seed)):
            rows.append([task, seed, r["algo"],
                         r["steps_to_target"] if r["steps_to_target"] is not None
                         else f"> {r['real_steps_trained']}",
                         r["final_return"], r["best_return"], r["wall_s"],
                         " ".join(f"{p['real_steps']}:{p['return']:.1f}" for p in r["curve"])])
        lr = c["loop_reach"]
        rows.append([task, seed, "loop (twinrl run), data before the deployed policy",
                     lr["data_steps"] if lr["round"] is not None else f"> {lr['data_steps']}",
                     lr["score"], None, None, f"round {lr['round']}"])
        rows.append([task, seed, "loop, incl. that round's deployment",
                     lr["all_steps"] if lr["round"] is not None else f"> {lr['all_steps']}",
                     c["loop_real_return"], None, None, "recorded episodes' mean"])
        rows.append([task, seed, "(d) sim-only policy, no adaptation (final round)",
                     c["rounds"][-2]["real_steps"] if len(c["rounds"]) > 1 else None,
                     c["sim_policy_real_return"], None, None, "data steps it was made from"])
    report.print_table(f"real-twin steps to {FRACTION:.0%} of the oracle return",
                       ["task", "seed", "method", "real steps to target", "final return",
                        "best return", "wall s", "return at eval (steps:return)"], rows)
    report.print_table("model-free vs loop",
                       ["task", "seed", "oracle", "target", "loop data steps",
                        "best model-free / loop data steps", "loop steps incl. deployment",
                        "best model-free / loop steps incl. deployment"],
                       [[c["task"], c["seed"], c["oracle_return"], c["target"],
                         c["loop_reach"]["data_steps"], fmt_ratio(c["ratio_best_to_loop"]),
                         c["loop_reach"]["all_steps"],
                         fmt_ratio(c["ratio_best_to_loop_all_steps"])]
                        for c in comparisons])

    plot = args.plot or args.out / "sim2real.png"
    for c in comparisons:
        curves = {f"{r['algo']} seed {r['seed']}": ([p["real_steps"] for p in r["curve"]],
                                                    [p["return"] for p in r["curve"]])
                  for r in runs if r["task"] == c["task"] and r["seed"] == c["seed"]}
        curves[f"loop seed {c['seed']}"] = ([c["loop_reach"]["data_steps"]],
                                            [c["loop_reach"]["score"] or c["loop_real_return"]])
        path = plot if len(comparisons) == 1 else plot.with_name(
            f"{plot.stem}_{c['task']}_s{c['seed']}{plot.suffix}")
        report.plot_curves(path, curves, "real-twin steps", "return (deterministic policy)",
                           title=f"{c['task']}: model-free on the real twin vs loop",
                           hline=(c["target"], f"{FRACTION:.0%} of oracle"))
        print(f"plot: {path}")
    print(f"results: {write_result(args.out / 'sim2real.json', out, args)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
