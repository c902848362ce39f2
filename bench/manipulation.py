"""The manipulation suite's costs and trajectory optimisation's success, per task.

Per task (``peg_insertion``, ``spatula_flipping``, ``needle_threading``; float32, CPU unless JAX
finds an accelerator):
- compile seconds of the batched ``step`` and of the episode-return gradient;
- forward env-steps/s (control steps, each ``frame_skip`` physics steps): single env, vmap 16;
- gradient env-steps/s of ``jax.value_and_grad`` of an episode's return w.r.t. its actions:
  single, vmap 16;
- trajectory optimisation from the privileged state (``twinrl.learn.trajopt``, first order with
  a line search, ``--iterations`` improvements from zero actions, then up to ``--restarts``
  more attempts on the starts not solved, from the next initial guess of ``twinrl.learn.plans.initial_guesses``)
  on ``--starts`` random initial states: success rate (the task's ``success`` at the episode's
  end), on the first attempt and in all, which attempt solved how many, and seconds per solved
  trajectory (wall time of all the solves / solved ones; compile excluded and reported apart);
- frames/s of a 64x64 RGB-D + segmentation image of the task's scene from its camera mount
  (``ArmTask.render``: hard image, and soft with its gradient w.r.t. the mount pose);
- the fraction of the mount's workspace (a 5 x 5 x 3 lattice of poses, several reset states)
  from which the task's target (``target_geoms``) shows at least ``--min-pixels`` pixels;
- the optimised plans replayed open loop on the real twin without perturbation and on the default
  real twins of seeds 0..N-1 (``--replay N``): the gap the Real2Sim/Sim2Real loop has to close.

Prints a table and writes ``DIR/manipulation.json`` (``--out DIR``); the optimised action
sequences go to ``DIR/<task>_plans.npz`` (the demonstrations the imitation stage learns from).

    python bench/manipulation.py --out bench/results
    python bench/manipulation.py --tasks peg_insertion --starts 20 --iterations 40
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

from twinrl import envs
from twinrl.learn import plans as plans_lib
from twinrl.learn import trajopt
from twinrl.report import print_table
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)

TASKS = ("peg_insertion", "spatula_flipping", "needle_threading")


def _timed(fn, *args):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0, out


def _best(fn, *args, repeats: int) -> float:
    jax.block_until_ready(fn(*args))
    return min(_timed(fn, *args)[0] for _ in range(repeats))


def throughput(env, repeats: int) -> dict:
    T = env.episode_length
    key = jax.random.PRNGKey(0)
    s1 = env.reset(key)
    s16 = jax.vmap(env.reset)(jax.random.split(key, 16))
    a1 = 0.5 * jax.random.uniform(key, (T, env.action_size), minval=-1.0, maxval=1.0)
    a16 = jnp.broadcast_to(a1, (16,) + a1.shape)

    def ret(s, a):
        return env.unroll(s, a)[1].sum()

    fwd1, fwd16 = jax.jit(ret), jax.jit(jax.vmap(ret))
    grad1 = jax.jit(jax.value_and_grad(ret, argnums=1))
    grad16 = jax.jit(jax.vmap(jax.value_and_grad(ret, argnums=1)))
    out = {"T": T, "frame_skip": int(env.config.frame_skip), "nv": env.sim.nv,
           "action_size": env.action_size}
    out["compile_forward_s"], _ = _timed(fwd16, s16, a16)
    out["compile_grad_s"], _ = _timed(grad16, s16, a16)
    _timed(fwd1, s1, a1)
    _timed(grad1, s1, a1)
    out["forward_steps_per_s_single"] = T / _best(fwd1, s1, a1, repeats=repeats)
    out["forward_steps_per_s_vmap16"] = 16 * T / _best(fwd16, s16, a16, repeats=repeats)
    out["grad_steps_per_s_single"] = T / _best(grad1, s1, a1, repeats=repeats)
    out["grad_steps_per_s_vmap16"] = 16 * T / _best(grad16, s16, a16, repeats=repeats)
    return out


def render_rate(env, repeats: int) -> dict:
    s = env.reset(jax.random.PRNGKey(0))
    coords = jnp.zeros(3, jnp.float32)
    hard = jax.jit(lambda c: env.render(s, c, size=64).depth)
    soft = jax.jit(jax.grad(lambda c: jnp.sum(env.render(s, c, tau=1.0, size=64).rgb)))
    _timed(hard, coords)
    _timed(soft, coords)
    return {"render_fps_64": 1.0 / _best(hard, coords, repeats=repeats),
            "render_grad_fps_64": 1.0 / _best(soft, coords, repeats=repeats),
            "ngeom_drawn": int(env.renderer.ngeom)}


def visibility(env, states: int, min_pixels: int, grid: int = 5) -> dict:
    """Fraction of (state, camera pose) pairs from which the task's target is visible: at least
    ``min_pixels`` of its geoms' pixels in the 64x64 hard segmentation, over ``states`` reset
    states and a ``grid`` x ``grid`` x 3 lattice of the mount's (azimuth, elevation, distance)."""
    mount = env.mount
    ids = jnp.asarray(env.target_geom_ids)
    az = np.linspace(*mount.azimuth, grid + 2)[1:-1]
    el = np.linspace(*mount.elevation, grid + 2)[1:-1]
    dist = np.linspace(*mount.distance, 5)[1:-1]
    poses = np.array([mount.coords_of([a, e, d]) for a in az for e in el for d in dist],
                     np.float32)
    count = jax.jit(jax.vmap(lambda s, c: jnp.sum(jnp.isin(
        env.render(s, c, size=64).segmentation, ids)), in_axes=(None, 0)))
    seen = []
    for k in jax.random.split(jax.random.PRNGKey(7), states):
        seen.append(np.asarray(count(env.reset(k), jnp.asarray(poses))) >= min_pixels)
    seen = np.array(seen)
    default = np.asarray(count(env.reset(jax.random.PRNGKey(7)),
                               jnp.asarray(mount.default, jnp.float32)[None]))[0]
    return {"visible_fraction": float(seen.mean()), "visible_poses": int(poses.shape[0]),
            "visible_min_pixels": min_pixels, "target_pixels_default_pose": int(default)}


def replay(env, plans: np.ndarray, keys: np.ndarray, twin_seeds, zero: bool = False) -> float:
    """Success rate of the optimised open-loop plans replayed on real twins (``RealTwin`` of each
    of ``twin_seeds`` in turn; ``zero``: without perturbation), each from its plan's start state.
    Evaluation code: ``RealTwin.success`` judges the twin's true state at its true tool."""
    from twinrl.real.perturbation import Perturbation
    from twinrl.real.twin import RealTwin

    reset = jax.jit(env.reset)
    wins = []
    for i, (a, key) in enumerate(zip(plans, keys)):
        seed = int(twin_seeds[i % len(twin_seeds)])
        twin = RealTwin(env.name, seed=seed, perturbation=Perturbation.none() if zero else None)
        s = reset(jnp.asarray(key))
        twin.reset(seed=i, options={"qpos": np.asarray(s.pipeline_state.qpos, np.float64),
                                    "qvel": np.asarray(s.pipeline_state.qvel, np.float64)})
        for action in a:
            twin.step(action)
        wins.append(twin.success())
        twin.close()
    return float(np.mean(wins))


def _meta(args) -> dict:

    return {"trajopt": {"order": 1, "step_size": args.step_size,
                                      "line_search_steps": 6, "iterations": args.iterations,
                                      "restarts": args.restarts}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="*", default=list(TASKS), choices=TASKS)
    p.add_argument("--starts", type=int, default=50, help="random initial states per task")
    p.add_argument("--iterations", type=int, default=60, help="trajopt improvements per start")
    p.add_argument("--batch", type=int, default=10, help="starts optimised together (vmap)")
    p.add_argument("--restarts", type=int, default=2,
                   help="re-optimise unsolved starts up to N times, each from the next initial "
                        "guess (arm tasks with an approach point: the approach, the approach "
                        "stopping 2 cm short, smooth random actions; others: random actions)")
    p.add_argument("--step-size", type=float, default=0.5, help="trajopt's largest step")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--replay", type=int, default=5, metavar="N",
                   help="replay the optimised plans open loop on the unperturbed twin and on the "
                        "default real twins of seeds 0..N-1 (0: skip)")
    p.add_argument("--skip", nargs="*", default=[],
                   choices=("throughput", "render", "visibility", "trajopt"))
    p.add_argument("--visibility-states", type=int, default=4,
                   help="reset states over which the target's visibility is counted")
    p.add_argument("--min-pixels", type=int, default=10,
                   help="target pixels (of 64x64) that count as visible")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    config = trajopt.TrajoptConfig(order=1, step_size=args.step_size, line_search_steps=6)
    rows = []
    for name in args.tasks:
        env = envs.make(name)
        row = {"task": name}
        if "throughput" not in args.skip:
            print(f"[bench] {name}: throughput ...", flush=True)
            row.update(throughput(env, args.repeats))
        if "render" not in args.skip:
            print(f"[bench] {name}: render ...", flush=True)
            row.update(render_rate(env, args.repeats))
        if "visibility" not in args.skip:
            print(f"[bench] {name}: visibility over the mount's workspace ...", flush=True)
            row.update(visibility(env, args.visibility_states, args.min_pixels))
        if "trajopt" not in args.skip:
            print(f"[bench] {name}: trajopt on {args.starts} starts ...", flush=True)
            res = plans_lib.plan(env, args.starts, args.iterations, args.batch, args.seed,
                                 config, args.restarts,
                                 say=lambda s: print(f"[bench] {s}", flush=True))
            plans_lib.save(args.out / f"{name}_plans.npz", res)
            plans, keys = res.pop("plans"), res.pop("keys")
            res.pop("success")
            row.update(res)
            if args.replay:
                print(f"[bench] {name}: replaying the plans on real twins ...", flush=True)
                row["replay_success_zero_twin"] = replay(env, plans, keys, [0], zero=True)
                row["replay_success_real_twins"] = replay(env, plans, keys, range(args.replay))
        rows.append(row)
        write_result(args.out / "manipulation.json", {"meta": _meta(args), "tasks": rows}, args)
    cols = [("task", "task"), ("compile fwd s", "compile_forward_s"),
            ("compile grad s", "compile_grad_s"), ("fwd 1", "forward_steps_per_s_single"),
            ("fwd vmap16", "forward_steps_per_s_vmap16"), ("grad 1", "grad_steps_per_s_single"),
            ("grad vmap16", "grad_steps_per_s_vmap16"), ("render fps", "render_fps_64"),
            ("render+grad fps", "render_grad_fps_64"), ("target visible", "visible_fraction"),
            ("trajopt success", "success_rate"), ("first attempt", "success_rate_first_attempt"),
            ("s / solved", "seconds_per_solved"), ("trajopt compile s", "trajopt_compile_s"),
            ("replay: zero twin", "replay_success_zero_twin"),
            ("replay: real twins", "replay_success_real_twins")]
    print_table(f"manipulation suite (control steps/s, {jax.devices()[0].platform})",
                [c for c, _ in cols], [[r.get(k) for _, k in cols] for r in rows])
    path = write_result(args.out / "manipulation.json", {"meta": _meta(args), "tasks": rows}, args)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
