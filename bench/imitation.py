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

``--run TASK=DIR`` instead repeats a ``twinrl run`` loop's imitation stage (DIR: its output
directory; its last round's identified twin, plans and imitation settings) with each of
``--seeds``, and scores every round's actor on ``--episodes`` starts other than the
``eval_episodes`` ones the stage chooses its round on (``ImitationConfig.keep``): how much the
rounds swing, and what keeping the best one is worth against keeping the last. Writes
``DIR/imitation_rounds.json`` (``--out DIR``).

    python bench/imitation.py --run spatula_flipping=runs/spatula --seeds 0 1 2 --out bench/results
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, jaxconfig)
import jax
import jax.numpy as jnp
import numpy as np

from twinrl import envs
from twinrl.learn import imitation
from twinrl.report import print_table
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)

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
    p.add_argument("--run", metavar="TASK=DIR", help="repeat a loop run's imitation stage")
    p.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2], help="with --run")
    p.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="ImitationConfig fields (JSON values), over the bench's own settings or, "
                        "with --run, over the stage's")
    args = p.parse_args(argv)
    if args.run:
        return rounds_of_run(args)
    sets = _sets(args.set)
    configs = {obs: _config(dict(   # checked before any task's work starts
        observation=obs, dagger_rounds=args.rounds, dagger_episodes=args.dagger_episodes,
        relabel_every=args.relabel_every, relabel_iterations=args.relabel_iterations,
        solved_labels=args.solved_labels, fit_steps=args.fit_steps,
        eval_episodes=args.episodes), sets) for obs in args.observations}
    rows = []
    for name in args.tasks:
        demos = imitation.load_demonstrations(args.plans / f"{name}_plans.npz")
        env = envs.make(name)
        for obs in args.observations:
            cfg = configs[obs]
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
            write_result(args.out / "imitation.json", {"rows": rows}, args)
    cols = [("task", "task"), ("observation", "observation"), ("demos", "demonstrations"),
            ("success: cloning", "success_cloning"), ("success: DAgger", "success"),
            ("return", "return"), ("expert labels", "labels"), ("wall s", "wall_s")]
    print_table(f"imitation in sim ({args.episodes} fresh starts)", [c for c, _ in cols],
                [[r[k] for _, k in cols] for r in rows])
    path = write_result(args.out / "imitation.json", {"rows": rows}, args)
    print(f"wrote {path}")
    return 0


def _sets(items) -> dict:
    """``--set FIELD=VALUE ...`` as {field: JSON value}; a malformed item is a one-line error."""
    out = {}
    for kv in items:
        k, eq, v = kv.partition("=")
        if not eq or not k:
            _bad(f"--set takes FIELD=VALUE, got {kv!r}")
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            _bad(f"--set {kv}: the value is not JSON (strings need quotes: {k}='\"...\"')")
    return out


def _config(base: dict, sets: dict):
    """ImitationConfig of ``base`` with ``sets`` over it; an unknown field or a bad value is a
    one-line error."""
    try:
        return imitation.ImitationConfig.from_dict({**base, **sets})
    except (TypeError, ValueError) as e:
        _bad(f"--set: {e}")


def _bad(message: str):
    print(f"bench/imitation.py: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def rounds_of_run(args) -> int:
    """``--run``: the loop's imitation stage again per seed, every round scored on other starts."""
    from twinrl.envs.system import System

    task, _, run = args.run.partition("=")
    if task not in TASKS or not run:
        _bad(f"--run takes TASK=DIR with TASK one of {', '.join(TASKS)}: {args.run!r}")
    if not (Path(run) / "summary.json").is_file():
        _bad(f"--run {args.run}: no summary.json there (a twinrl run's output)")
    summary = json.loads((Path(run) / "summary.json").read_text())
    rdir = Path(run) / f"round{summary['final']['round']}"
    env = envs.make(task, system=System.load(rdir / "system.json"))
    stage = json.loads((rdir / "actor" / "run.json").read_text())["config"]
    cfg = _config({**stage, "demonstrations": ""}, _sets(args.set))
    demos = imitation.load_demonstrations(rdir / "plans.npz")
    observe, _ = imitation.make_observer(env, cfg)
    n = int(args.episodes)

    def scorer(net):
        @jax.jit
        def score(params, key):  # starts and mount poses of their own (not the stage's)
            ep = imitation.actor_episodes(env, observe, lambda o: net.apply(params, o), cfg,
                                          key, n)
            return jnp.mean(ep.success), jnp.mean(ep.rewards.sum(1))
        return score

    rows = []
    for seed in args.seeds:
        t0, each = time.perf_counter(), []
        net, _, m = imitation.train(env, cfg, seed, demos=demos,
                                    round_fn=lambda r, p: each.append(p))
        score = scorer(net)
        other = [float(score(p, jax.random.PRNGKey(10_000))[0]) for p in each]
        kept = int(np.argmax(m["kept"]))
        rows.append({"seed": seed, "stage_success": m["success"], "other_success": other,
                     "kept_round": kept, "kept": other[kept], "last": other[-1],
                     "labels_solved": m["labels_solved"], "wall_s": time.perf_counter() - t0})
        print(f"[bench] {task} seed {seed}: stage's starts {np.round(m['success'], 2).tolist()}, "
              f"other starts {np.round(other, 2).tolist()}, kept round {kept} "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
        write_result(args.out / "imitation_rounds.json", {"rows": rows}, args)
    print_table(f"{task}: the loop's imitation stage ({cfg.eval_episodes} starts choose the round; "
                f"{n} other starts score it)", ["seed", "stage's starts per round",
                "other starts per round", "kept round", "kept", "last"],
                [[r["seed"], " / ".join(f"{x:.2f}" for x in r["stage_success"]),
                  " / ".join(f"{x:.2f}" for x in r["other_success"]), r["kept_round"],
                  r["kept"], r["last"]] for r in rows])
    kept, last = (float(np.mean([r[k] for r in rows])) for k in ("kept", "last"))
    print(f"mean over {len(rows)} seeds, other starts: kept {kept:.3f}, last {last:.3f}")
    path = write_result(args.out / "imitation_rounds.json", {"rows": rows,
                                                           "mean_kept": kept, "mean_last": last})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
