"""Imitation of trajectory optimisation on the manipulation suite: success of the state actor and
of the image actor in the simulator (SAM-RL's actor; ``twinrl.learn.imitation``).

Per task: the demonstrations are the successful plans of ``bench/manipulation.py``
(``DIR/<task>_plans.npz``, ``--plans DIR``); behaviour cloning, then ``--rounds`` DAgger rounds
labelled by trajectory optimisation; success rate and mean return over ``--episodes`` fresh start
states (not the demonstrations'), per round, for ``--observations`` (``state``: the privileged
vector; ``pixels``: joint angles/velocities + a 64 x 64 RGB-D + target-mask image from a mount
pose drawn per episode). Prints a table and writes ``DIR/imitation.json`` (``--out DIR``).

    python bench/manipulation.py --skip throughput render visibility --out bench/results
    python bench/imitation.py --plans bench/results --out bench/results
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


from twinrl import envs
from twinrl.learn import imitation
from twinrl.report import print_table, run_meta, write_json

TASKS = ("peg_insertion", "spatula_flipping", "needle_threading")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="*", default=list(TASKS), choices=TASKS)
    p.add_argument("--plans", type=Path, default=Path("bench/results"),
                   help="directory of bench/manipulation.py's <task>_plans.npz")
    p.add_argument("--observations", nargs="*", default=["state", "pixels"],
                   choices=("state", "pixels"))
    p.add_argument("--rounds", type=int, default=2, help="DAgger rounds after cloning")
    p.add_argument("--dagger-episodes", type=int, default=10)
    p.add_argument("--relabel-every", type=int, default=5)
    p.add_argument("--relabel-iterations", type=int, default=10)
    p.add_argument("--solved-labels", action="store_true",
                   help="keep only the DAgger labels whose improved plan solves the task")
    p.add_argument("--fit-steps", type=int, default=imitation.ImitationConfig.fit_steps)
    p.add_argument("--episodes", type=int, default=50, help="evaluation episodes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    rows = []
    for name in args.tasks:
        demos = imitation.load_demonstrations(args.plans / f"{name}_plans.npz")
        env = envs.make(name)
        for obs in args.observations:
            cfg = imitation.ImitationConfig(
                observation=obs, dagger_rounds=args.rounds, dagger_episodes=args.dagger_episodes,
                relabel_every=args.relabel_every, relabel_iterations=args.relabel_iterations,
                solved_labels=args.solved_labels,
                fit_steps=args.fit_steps, eval_episodes=args.episodes)
            say = lambda r, row: print(  # noqa: E731
                f"[bench] {name} {obs}: round {r}: pairs {int(row['pairs'])}, loss "
                f"{row['loss']:.4f}, success {row['success']:.2f}, return {row['return']:.1f}, "
                f"labels solved {row['labels_solved']:.2f} "
                f"({row['wall_s']:.0f} s)", flush=True)
            t0 = time.perf_counter()
            _, _, m = imitation.train(env, cfg, args.seed, demos=demos, progress_fn=say)
            rows.append({"task": name, "observation": obs, "demonstrations": len(demos.keys),
                         "success_cloning": m["success"][0], "success": m["success"][-1],
                         "return": m["return"][-1], "pairs": m["pairs"][-1],
                         "labels": sum(m["labels"]), "wall_s": time.perf_counter() - t0,
                         "rounds": m})
            write_json(args.out / "imitation.json", {"meta": run_meta(args), "rows": rows})
    cols = [("task", "task"), ("observation", "observation"), ("demos", "demonstrations"),
            ("success: cloning", "success_cloning"), ("success: DAgger", "success"),
            ("return", "return"), ("expert labels", "labels"), ("wall s", "wall_s")]
    print_table(f"imitation in sim ({args.episodes} fresh starts)", [c for c, _ in cols],
                [[r[k] for _, k in cols] for r in rows])
    path = write_json(args.out / "imitation.json", {"meta": run_meta(args), "rows": rows})
    print(f"wrote {path}")
    return 0



if __name__ == "__main__":
    sys.exit(main())
