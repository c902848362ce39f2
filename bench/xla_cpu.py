"""XLA's CPU fusion emitters against MJX: run time of kinematic chains, the arm tasks and the
renderer, with the emitters on (the pinned jaxlib's default) and off (twinrl's default, set on
import: ``twinrl._jaxconfig``).

Each setting runs in its own process (XLA reads ``XLA_FLAGS`` once, when JAX starts), with the
compilation cache off so neither setting loads the other's executables:
- ``smooth.kinematics`` (stock MJX) of chains of 2..9 hinge links whose frames are rotated (each
  body's ``quat``), ms per call;
- each manipulation task, forward, single env: one control step (``frame_skip`` physics steps)
  and a whole episode (``env.unroll``: the steps inside one ``lax.scan``, as every trainer and
  trajopt runs them), ms per physics step, and compile seconds;
- the renderer: a 64x64 image of ``peg_insertion``'s scene, batch 16 over camera poses, hard
  (depth) and soft with its gradient w.r.t. the pose, frames/s.

    python bench/xla_cpu.py --out bench/results
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

SETTINGS = {"emitters on": "--xla_cpu_use_fusion_emitters=true",
            "emitters off": "--xla_cpu_use_fusion_emitters=false"}
TASKS = ("peg_insertion", "spatula_flipping", "needle_threading")


def _best(f, *args, repeats=3):
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(f(*args))
    compile_s = time.perf_counter() - t0
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        best = min(best, time.perf_counter() - t0)
    return compile_s, best


def _chain(n: int) -> str:
    body = "".join('<body pos="0 0 0.1" quat="0.7071 0.7071 0 0"><joint type="hinge" axis="0 0 1"/>'
                   '<geom type="capsule" size="0.02" fromto="0 0 0 0 0 0.1"/>' for _ in range(n))
    return f"<mujoco><worldbody>{body}{'</body>' * n}</worldbody></mujoco>"


def measure(depths, tasks) -> dict:
    import twinrl  # noqa: F401  (the JAX settings; XLA_FLAGS already holds the flag)
    import jax
    import jax.numpy as jnp
    import mujoco
    from mujoco import mjx
    from mujoco.mjx._src import smooth

    from twinrl import envs

    out = {"xla_flags": os.environ.get("XLA_FLAGS", ""), "chain_ms": {}, "tasks": {}}
    for n in depths:
        mj = mujoco.MjModel.from_xml_string(_chain(n))
        m, d = mjx.put_model(mj), mjx.make_data(mj)
        _, t = _best(jax.jit(lambda d, m=m: smooth.kinematics(m, d)), d)
        out["chain_ms"][str(n)] = 1e3 * t
    for name in tasks:
        env = envs.make(name)
        s = env.reset(jax.random.PRNGKey(0))
        a = jnp.zeros(env.action_size)
        c, t = _best(jax.jit(env.step), s, a)
        steps = env.episode_length * env.config.frame_skip
        plan = jnp.zeros((env.episode_length, env.action_size))
        cu, tu = _best(jax.jit(lambda s, p: env.unroll(s, p)[1].sum()), s, plan)
        out["tasks"][name] = {"compile_s": c,
                              "ms_per_physics_step": 1e3 * t / env.config.frame_skip,
                              "episode_compile_s": cu,
                              "episode_ms_per_physics_step": 1e3 * tu / steps}
    env = envs.make("peg_insertion")
    s = env.reset(jax.random.PRNGKey(0))
    poses = jnp.linspace(-0.5, 0.5, 16)[:, None] * jnp.ones((16, 3))
    hard = jax.jit(jax.vmap(lambda c: env.render(s, c, size=64).depth))
    soft = jax.jit(jax.vmap(jax.grad(lambda c: jnp.sum(env.render(s, c, tau=1.0, size=64).rgb))))
    out["render_fps_64_b16"] = 16 / _best(hard, poses)[1]
    out["render_grad_fps_64_b16"] = 16 / _best(soft, poses)[1]
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--depths", type=int, nargs="*", default=[2, 4, 6, 7, 8, 9])
    p.add_argument("--tasks", nargs="*", default=list(TASKS), choices=TASKS)
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(measure(args.depths, args.tasks)))
        return 0
    results = {}
    for label, flag in SETTINGS.items():
        print(f"[bench] {label} ...", flush=True)
        env = dict(os.environ, TWINRL_CACHE_DIR="off",
                   XLA_FLAGS=f"--xla_cpu_multi_thread_eigen=true {flag}")
        cmd = [sys.executable, __file__, "--child", "--depths", *map(str, args.depths),
               "--tasks", *args.tasks]
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
        results[label] = json.loads(done.stdout.strip().splitlines()[-1])
    from twinrl.report import print_table, write_json

    on, off = results["emitters on"], results["emitters off"]
    rows = [[f"kinematics, chain of {n} (ms)", on["chain_ms"][str(n)], off["chain_ms"][str(n)]]
            for n in args.depths]
    for name in args.tasks:
        rows.append([f"{name}: ms / physics step", on["tasks"][name]["ms_per_physics_step"],
                     off["tasks"][name]["ms_per_physics_step"]])
        rows.append([f"{name}: compile s", on["tasks"][name]["compile_s"],
                     off["tasks"][name]["compile_s"]])
        rows.append([f"{name}: episode (unroll), ms / physics step",
                     on["tasks"][name]["episode_ms_per_physics_step"],
                     off["tasks"][name]["episode_ms_per_physics_step"]])
        rows.append([f"{name}: episode compile s", on["tasks"][name]["episode_compile_s"],
                     off["tasks"][name]["episode_compile_s"]])
    rows.append(["render 64x64 b16 (frames/s)", on["render_fps_64_b16"], off["render_fps_64_b16"]])
    rows.append(["render + grad 64x64 b16 (frames/s)", on["render_grad_fps_64_b16"],
                 off["render_grad_fps_64_b16"]])
    for r in rows:
        r.append(r[1] / r[2] if r[2] else None)
    print_table("XLA CPU fusion emitters (cache off, one process each)",
                ["measure", "emitters on", "emitters off", "on / off"], rows)
    path = write_json(args.out / "xla_cpu.json", {"cpu_count": os.cpu_count(), **results})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
