"""The image observation's pose fit from random mount poses, and what it costs the image actor.

A ``"pose"`` image actor (the needle's and the peg's in ``twinrl run``) acts on the target's pose
fitted to one depth image (``ArmTask.fit_target_pose``). This takes a run's identified twin
(``--run TASK=DIR``, its last round's ``system.json`` and actor) and measures, in that twin:

1. **The fit** at ``--views`` random (start state, mount pose) pairs drawn as the imitation stage
   draws its views (``imitation.episode_coords``), for each ``--hinge-grids`` value
   (``ArmConfig.pose_hinge_grid``: 0 is the default, local restarts only) and each
   ``--image-sizes`` value (``ArmConfig.image_size``, the images' width and height; default the
   run's): the share of views
   whose fit is off by more than ``--tol`` in any target joint (m for slides, rad for hinges,
   modulo the target's symmetry), which joint is worst there, the fit's RMS residual (mm) on good
   and bad views (a wrong fit at an exact residual is a view that cannot tell), observations/s.
2. **The actor** on ``--episodes`` random views (the stage's own draw: ``imitation
   .actor_episodes``'s starts and poses, seed 10,000), its estimate from: ``fit`` (each step's own
   fit, as deployed), ``best`` (the fit with the most target pixels so far: the target is at
   rest), ``truth`` (perfect perception: ``estimate_from_obs``): success, and success split by
   whether the pose the actor used stayed within ``--episode-tol`` throughout; the fit's hinge
   grid ``--actor-hinge-grid``, its images ``--actor-image-size`` pixels wide (a pose actor
   reads the fitted pose, not the pixels: one actor, any image size).

Prints two tables and writes ``OUT/pose_views.json``. Needle, 2 cores: ~1-2 min per fit row
and per actor mode.

    python bench/pose_views.py --run needle_threading=RUN --out B
    python bench/pose_views.py --run needle_threading=RUN --hinge-grids 0 4 8 --modes fit --out B
    python bench/pose_views.py --run needle_threading=RUN --image-sizes 64 128 \
        --actor-image-size 128 --modes fit --out B
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, _jaxconfig)
import jax
import jax.numpy as jnp
import numpy as np

from twinrl.learn import imitation
from twinrl.report import print_table, run_meta, write_json

MODES = ("fit", "best", "truth")


def _bad(message: str):
    print(f"bench/pose_views.py: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def load_run(spec: str):
    """``(task, round dir)`` of ``--run TASK=DIR``, or a one-line error."""
    task, _, run = spec.partition("=")
    if not run or not (Path(run) / "summary.json").is_file():
        _bad(f"--run takes TASK=DIR, DIR a twinrl run's output (with summary.json): {spec!r}")
    summary = json.loads((Path(run) / "summary.json").read_text())
    if summary.get("env") != task:
        _bad(f"--run {spec}: that run is of {summary.get('env')!r}, not {task!r}")
    rdir = Path(run) / f"round{summary['final']['round']}"
    if not (rdir / "actor").is_dir():
        _bad(f"--run {spec}: no image actor in {rdir}")
    return task, rdir


def make_env(task, rdir, hinge_grid: int = 0, image_size: int | None = None):
    """The task in the round's identified twin, at ``image_size`` (default the run's)."""
    from twinrl.envs.system import System
    from twinrl.loop.arm import run_env

    size = {} if image_size is None else {"image_size": image_size}
    env = run_env(rdir.parent, System.load(rdir / "system.json"), pose_hinge_grid=hinge_grid,
                  **size)
    if not env.target_joints:
        _bad(f"{task} has no target_joints: its image observation fits no pose")
    return env


def true_pose(env, state):
    """The target joints' true values, hinges modulo the target's symmetry (evaluation)."""
    return env._wrap_target_pose(env.state_from_obs(state.obs)[0][np.asarray(env.target_joints)])


def pose_error(env, fitted, truth):
    """Per joint |fitted - truth|, hinges taken modulo the target's symmetry."""
    return jnp.abs(env._wrap_target_pose(fitted - truth))  # wraps the hinges only


def fit_rows(env, cfg, views: int, tol: float) -> dict:
    """Part 1 for one environment (one ``pose_hinge_grid``)."""
    def one(k):
        k_cam, k_reset = jax.random.split(k)
        s = env.reset(k_reset)
        o = env.image_observation(s, imitation.episode_coords(env, cfg, k_cam),
                                  keys=("pose", "support"))
        return pose_error(env, o["pose"], true_pose(env, s)), o["support"]

    f = jax.jit(jax.vmap(one))
    keys = jax.random.split(jax.random.PRNGKey(5), views)
    err, support = (np.asarray(x) for x in f(keys))
    t = time.perf_counter()
    jax.block_until_ready(f(keys))
    rate = views / (time.perf_counter() - t)
    bad = err.max(1) > tol
    worst = np.bincount(err[bad].argmax(1), minlength=err.shape[1]) if bad.any() else []
    return {"hinge_grid": int(env.config.pose_hinge_grid),
            "image_size": int(env.config.image_size), "views": views,
            "bad": float(bad.mean()), "worst_joint_counts": [int(x) for x in worst],
            "median_err": np.median(err, 0).tolist(), "p90_err": np.percentile(err, 90, 0).tolist(),
            "rms_mm_good": float(np.median(support[~bad, 1])) if (~bad).any() else None,
            "rms_mm_bad": float(np.median(support[bad, 1])) if bad.any() else None,
            "obs_per_s": rate}


def actor_row(env, cfg, net, params, mode: str, episodes: int, tol: float) -> dict:
    """Part 2: the actor's episodes with the estimate from ``mode``."""
    T, P = env.episode_length, len(env.target_joints)

    def observe(s, c, best):
        o = env.image_observation(s, c, keys=("pose", "support"))
        truth = true_pose(env, s)
        pixels, pose = o["support"][0], o["pose"]
        better = pixels >= best[1]
        kept = (jnp.where(better, pose, best[0]), jnp.maximum(pixels, best[1]))
        used = {"fit": pose, "best": kept[0], "truth": truth}[mode]
        est = env.pose_estimate(s.obs[:14], used)
        return {"estimate": est}, kept, jnp.max(pose_error(env, used, truth))

    def episode(k_reset, c):
        def body(x, _):
            s, best = x
            obs, best, err = observe(s, c, best)
            return (env.step(s, net.apply(params, obs)), best), err

        (s, _), err = jax.lax.scan(body, (env.reset(k_reset), (jnp.zeros(P), jnp.asarray(-1.0))),
                                   None, length=T)
        return env.success(s.pipeline_state.qpos, s.pipeline_state.qvel), jnp.max(err)

    ks = jax.vmap(jax.random.split)(jax.random.split(jax.random.PRNGKey(10_000), episodes))
    coords = jax.vmap(lambda k: imitation.episode_coords(env, cfg, k))(ks[:, 0])
    f = jax.jit(jax.vmap(episode))
    out = [f(ks[i:i + 10, 1], coords[i:i + 10]) for i in range(0, episodes, 10)]
    ok, err = (np.concatenate([np.asarray(o[i]) for o in out]).astype(np.float64) for i in (0, 1))
    right = err <= tol
    return {"mode": mode, "image_size": int(env.config.image_size), "episodes": episodes,
            "success": float(ok.mean()),
            "estimate_right_throughout": float(right.mean()),
            "success_if_right": float(ok[right].mean()) if right.any() else None,
            "success_if_wrong": float(ok[~right].mean()) if (~right).any() else None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", required=True, metavar="TASK=DIR")
    ap.add_argument("--views", type=int, default=200, help="random views of the fit's part")
    ap.add_argument("--hinge-grids", type=int, nargs="*", default=[0, 8])
    ap.add_argument("--tol", type=float, default=0.005, help="a fit's tolerance (m / rad)")
    ap.add_argument("--episodes", type=int, default=50, help="the actor's part (0: skip)")
    ap.add_argument("--modes", nargs="*", choices=MODES, default=list(MODES))
    ap.add_argument("--actor-hinge-grid", type=int, default=0,
                    help="the pose fit's hinge grid in the actor's part")
    ap.add_argument("--image-sizes", type=int, nargs="*", default=[None], metavar="N",
                    help="the fit's images, N x N pixels (default the run's)")
    ap.add_argument("--actor-image-size", type=int, default=None, metavar="N",
                    help="the images in the actor's part (default the run's)")
    ap.add_argument("--episode-tol", type=float, default=0.01,
                    help="the used estimate's tolerance over an episode (m / rad)")
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    args = ap.parse_args(argv)
    if (args.views < 1 or args.episodes < 0 or args.actor_hinge_grid < 0
            or any(k < 0 for k in args.hinge_grids)
            or any(n is not None and n < 8 for n in [*args.image_sizes, args.actor_image_size])):
        ap.error("--views must be >= 1, --episodes and --hinge-grids >= 0, image sizes >= 8")
    task, rdir = load_run(args.run)
    from twinrl.learn.sensing import load_actor

    net, params, meta = load_actor(rdir / "actor")
    cfg = imitation.ImitationConfig.from_dict({**meta.get("config", {}), "demonstrations": ""})
    if cfg.observation != "pose":
        _bad(f"--run {args.run}: its actor reads {cfg.observation!r}, not a fitted pose")
    fits, actors = [], []
    for n in args.image_sizes:
        for k in args.hinge_grids:
            fits.append(fit_rows(make_env(task, rdir, k, n), cfg, args.views, args.tol))
            print(f"[bench] fit, {fits[-1]['image_size']} px, hinge grid {k}: "
                  f"{fits[-1]['bad']:.0%} of views off", flush=True)
    env = make_env(task, rdir, args.actor_hinge_grid, args.actor_image_size)
    for mode in args.modes if args.episodes else []:
        actors.append(actor_row(env, cfg, net, params, mode, args.episodes, args.episode_tol))
        print(f"[bench] actor, estimate {mode}: {actors[-1]['success']:.0%}", flush=True)
    size = int(env.config.image_size)
    if fits:
        print_table(f"{task}: the pose fit from {args.views} random views (off: any joint > "
                    f"{args.tol:g})", ["image", "hinge grid", "views off",
                                       "worst joint (counts)", "RMS mm good / off", "obs/s"],
                    [[f"{r['image_size']} px", r["hinge_grid"], f"{r['bad']:.1%}",
                      r["worst_joint_counts"],
                      " / ".join("-" if x is None else f"{x:.4f}"
                                 for x in (r["rms_mm_good"], r["rms_mm_bad"])),
                      f"{r['obs_per_s']:.0f}"] for r in fits])
    if actors:
        print_table(f"{task}: the run's image actor on {args.episodes} random views ({size} px, "
                    f"hinge grid {args.actor_hinge_grid})",
                    ["estimate", "success", f"estimate within {args.episode_tol:g} throughout",
                     "success: within / not"],
                    [[r["mode"], f"{r['success']:.0%}", f"{r['estimate_right_throughout']:.0%}",
                      " / ".join("-" if x is None else f"{x:.0%}"
                                 for x in (r["success_if_right"], r["success_if_wrong"]))]
                     for r in actors])
    path = write_json(args.out / "pose_views.json", {"meta": run_meta(args), "run": args.run,
                                                      "fits": fits, "actors": actors})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
