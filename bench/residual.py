"""Benchmark: does residual adaptation help on a real twin with an effect sysid cannot model?

The default real twins differ from the simulator only in ways ``PhysParams`` can express (plus
latency and noise), so after sysid the hybrid model has nothing left to learn and the residual
policy nothing to correct. Here each task's default twin (``seed``) gets, in addition, a constant
actuator offset (``Perturbation.actuator_offset``: force = gain * (ctrl + offset), a motor driver's
zero error), which no ``PhysParams`` value reproduces. ``twinrl.loop.run`` then runs unchanged on
that twin (oracle off: it would not know the offset either), and the same unrecorded evaluation
episodes (same start states) score

- **before**: pi_sim alone, the policy learned in the identified simulator;
- **after**: pi_sim + delta, the residual trained through the hybrid model fitted on the real data;

with the hybrid model's held-out one-step RMSE against the identified simulator's (does the learned
dynamics see the offset?) and whether the loop's gate (``residual.accept``) deployed delta at all.
Prints a table and writes ``bench/results/residual.json``.
Run: ``.venv/bin/python bench/residual.py [--offset 0.2] [--seeds 0] [--rounds 1]
[--out-dir runs/bench_residual]`` (one loop run per seed: ~6 min a round on 2 cores).

Measured (cartpole, seed 0, offset 0.2, 1 round): before the gate, delta lowered the real return
from 128.0 to 117.8; with it, delta is rejected (model return 98.8 -> 98.4) and the real return
stays 128.0. The hybrid model, fitted on round 0's 500 exciting transitions, predicts 98.8 for
pi_sim where the twin gives 128: too far off for its gradients to improve the real return.
With ``--rounds 2`` (hybrid refitted on 1,500 transitions, round 1's deployments included; one-step
RMSE 0.015 against the sim's 0.036) delta is accepted and lifts round 2's pi_sim from 41.8 to 58.1
on the same episodes, though round 2's PPO policy was itself worse than round 1's (71.4 in sim).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

import twinrl  # noqa: F401  (compilation cache)
from twinrl import loop, report
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)
from twinrl.real.perturbation import Perturbation

RESULTS = Path(__file__).resolve().parent / "results"


def one(task: str, seed: int, offset: float, out_dir: Path, episodes: int, rounds: int) -> dict:
    base = Perturbation.sample(task, seed)
    nu = len(base.gain_scale)
    pert = dataclasses.replace(base, actuator_offset=(offset,) * nu)
    cfg = loop.LoopConfig(oracle=False, eval_episodes=episodes, rounds=rounds)
    out = out_dir / f"{task}_s{seed}_off{offset:g}_r{rounds}"
    t0 = time.perf_counter()
    s = loop.run(task, out, cfg, seed=seed, resume=True, perturbation=pert)
    final = s["final"]
    prog = json.loads((out / "progress.json").read_text())["rounds"][f"round{rounds}"]
    return {"task": task, "seed": seed, "offset": offset, "rounds": rounds,
            "eval_episodes": episodes, "residual_accepted": final.get("residual_accepted"),
            "before": final.get("sim_policy_real_return"),
            "after": final.get("adapted_real_return"),
            "deployed_recorded": final.get("real_return"), "sim_return": final.get("sim_return"),
            "real_steps": final.get("real_steps"),
            "hybrid_rmse": prog.get("hybrid_rmse"), "sim_rmse": prog.get("hybrid_sim_rmse"),
            "param_rel_error": final.get("param_rel_error"),
            "wall_s": time.perf_counter() - t0, "run_dir": str(out)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", nargs="+", default=["cartpole_swingup"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--offset", type=float, default=0.2,
                    help="actuator offset in control units (actions are in [-1, 1])")
    ap.add_argument("--episodes", type=int, default=5, help="evaluation episodes, before and after")
    ap.add_argument("--rounds", type=int, default=1,
                    help="loop rounds (later rounds refit sysid and the hybrid model on the "
                         "deployed episodes too)")
    ap.add_argument("--out-dir", type=Path, default=Path("runs/bench_residual"))
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    results = []
    for task in args.tasks:
        for seed in args.seeds:
            results.append(one(task, seed, args.offset, args.out_dir, args.episodes,
                               args.rounds))
            write_result(args.out / "residual.json", {"results": results}, args)  # after every run
    rows = [[r["task"], r["seed"], r["offset"], r["rounds"], r["before"], r["after"],
             (r["after"] - r["before"]) if None not in (r["after"], r["before"]) else None,
             float(np.mean(r["sim_rmse"])) if r["sim_rmse"] else None,
             float(np.mean(r["hybrid_rmse"])) if r["hybrid_rmse"] else None,
             r["residual_accepted"], r["wall_s"]]
            for r in results]
    report.print_table("residual adaptation on a twin with an unmodeled actuator offset",
                       ["task", "seed", "offset", "rounds", "real before (pi_sim)",
                        "real after (+delta)", "gain", "sim 1-step RMSE", "hybrid 1-step RMSE",
                        "delta accepted", "wall s"], rows)
    write_result(args.out / "residual.json", {"results": results}, args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
