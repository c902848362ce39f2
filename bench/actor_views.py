"""What limits a loop's image actor from random views: its cloning, or what the view shows.

The issue's target for the SAM-RL actor is success from *random* camera poses in the identified
twin. An actor that acts on the target's pose fitted to the image (``observation="pose"``: peg,
needle) can only be as right as that fit, and from some poses the fit is wrong (the needle's eye
seen edge-on). For each ``--run TASK=DIR`` (a finished ``twinrl run`` directory: its last
round's actor and identified twin), ``--episodes`` fresh starts (keys from ``--key``, states no
stage saw) are run by the actor

- ``truth``: fed the true state where it reads a fitted pose (what cloning alone reaches: the
  ceiling of any view);
- ``random``: from a mount pose drawn per episode as the imitation stage's evaluation draws it
  (``imitation.episode_coords``): the loop's ``sim_success``;
- ``default``: from the mount's default pose;

and each random-view episode is scored by how often its view gives a fitted pose within 5 mm of
the truth (``plans.accurate``, per step). ``random`` is split at ``--good`` (the share of an
episode's steps whose estimate is right): success from the views that see the target right,
and from the others. With ``p_good`` the share of random views that are good, success from
random views is ``p_good * s_good + (1 - p_good) * s_bad``; ``s_good`` is bounded by ``truth``,
so ``need_bad`` = the success the bad views would need for the issue's 90 % shows how much of
the gap is the views'. Actors that read the target cloud (``"target"``, spatula) have no fitted
pose: their rows give the three successes and no split.

Prints a table and writes ``DIR/actor_views.json`` (``--out DIR``).

    python bench/actor_views.py --run needle_threading=runs/needle --episodes 100 --out DIR
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, jaxconfig)
import jax
import jax.numpy as jnp
import numpy as np

from twinrl.report import print_table, wilson_interval
from q_rank import _pct, evaluate_runs, load_run  # noqa: E402  (bench/q_rank.py: a run's round)

TARGET = 0.9
"""The issue's success target from random views."""


def split(success: np.ndarray, good_share: np.ndarray, good: float, target: float = TARGET):
    """Success from the random views split at ``good`` (an episode's share of steps whose fitted
    pose is right): ``p_good``, ``s_good``, ``s_bad`` and ``need_bad``, the success the bad views
    would need for ``target`` overall if the good ones stayed at ``s_good`` (above 1: out of
    reach whatever the actor does on them). None where a side is empty."""
    success, good_share = np.asarray(success, float), np.asarray(good_share, float)
    is_good = good_share >= good
    p = float(np.mean(is_good))
    s_good = float(np.mean(success[is_good])) if is_good.any() else None
    s_bad = float(np.mean(success[~is_good])) if (~is_good).any() else None
    need = None
    if s_good is not None and p < 1.0:
        need = (target - p * s_good) / (1.0 - p)
    return {"p_good": p, "s_good": s_good, "s_bad": s_bad, "need_bad": need}


def evaluate(task: str, run: Path, args) -> dict:
    from twinrl.learn.camera_choice import image_size, observer
    from twinrl.learn.common import held_episodes
    from twinrl.learn.imitation import ImitationConfig, episode_coords
    from twinrl.learn.plans import accurate

    summary, env, actor, ap, *_ = load_run(task, run)
    t0 = time.perf_counter()
    act = lambda o: actor.apply(ap, o)  # noqa: E731
    observe = observer(env, image_size(env, actor), keys=tuple(actor.obs_spec))
    pose = "estimate" in actor.obs_spec

    def true_observe(s, c):  # the fitted pose replaced by the truth it estimates
        return {"estimate": env.observe(*env.state_from_obs(s.obs), nominal=False)}

    keys = jax.random.split(jax.random.PRNGKey(args.key), args.episodes)
    k_cam = jax.random.fold_in(jax.random.PRNGKey(args.key), 1)
    rand = jax.vmap(lambda k: episode_coords(env, ImitationConfig(observation="pose"), k))(
        jax.random.split(k_cam, args.episodes))
    default = jnp.tile(jnp.asarray(env.mount.default, jnp.float32), (args.episodes, 1))

    @jax.jit
    def episodes(coords):
        ep = held_episodes(env, observe, act, keys, coords=coords)
        return ep.success, jnp.mean(accurate(ep.obs, ep.states, env), axis=1)

    rows = {}
    ok, share = (np.asarray(x) for x in episodes(rand))
    rows["random"] = ok
    rows["default"] = np.asarray(episodes(default)[0])
    if pose:
        run_true = jax.jit(lambda: held_episodes(env, true_observe, act, keys,
                                                 coords=default).success)
        rows["truth"] = np.asarray(run_true())
    out = {"task": task, "run": str(run), "twin_seed": summary.get("seed"),
           "episodes": args.episodes, "observation": "pose" if pose else "target",
           "loop_sim_success": summary["final"].get("sim_success")}
    for name, s in rows.items():
        lo, hi = wilson_interval(int(s.sum()), len(s))
        out[name] = {"success": float(s.mean()), "ci95": [lo, hi]}
    if pose:
        out["random"].update(split(ok, share, args.good))
        out["random"]["good"] = args.good
        out["random"]["accurate_steps"] = float(np.mean(share))
        out["random"]["success_per_episode"] = ok.tolist()
        out["random"]["good_share_per_episode"] = share.tolist()
    out["wall_s"] = time.perf_counter() - t0
    print(f"[bench] {task} {run.name}: random {out['random']['success']:.2f}, default "
          f"{out['default']['success']:.2f}, truth "
          f"{out['truth']['success'] if pose else float('nan'):.2f} ({out['wall_s']:.0f} s)",
          flush=True)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", nargs="+", required=True, help="TASK=DIR twinrl run directories")
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--good", type=float, default=0.9,
                   help="a random view is good where this share of its steps' fitted poses "
                        "are within 5 mm")
    p.add_argument("--key", type=int, default=555_000,
                   help="PRNG key of the starts and views (no stage of the loop drew these)")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    if args.episodes < 2 or not 0.0 < args.good <= 1.0:
        raise SystemExit("--episodes must be >= 2 and --good in (0, 1]")
    rows = evaluate_runs(args, evaluate, "actor_views.json")
    print_table(f"The image actor in its identified twin, {args.episodes} fresh starts",
                ["task", "twin", "true state", "random views", "default view",
                 "random views good", "success: good / other", "other views would need"],
                [[r["task"], r["twin_seed"], _pct(r.get("truth", {}).get("success")),
                  _pct(r["random"]["success"]), _pct(r["default"]["success"]),
                  _pct(r["random"].get("p_good")),
                  f"{_pct(r['random'].get('s_good'))} / {_pct(r['random'].get('s_bad'))}",
                  _pct(r["random"].get("need_bad"))] for r in rows])
    print(f"wrote {args.out / 'actor_views.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
