"""Trace reuse of the physics step and of the renderer's scene: ``Sim.step`` through one jitted
function against the step inlined into every function that takes it; renders of a task's state
through one jitted ``mjx.kinematics`` and a renderer equal by content against kinematics inlined
and renderers equal by identity.

``Sim.step`` calls ``twinrl.physics.integrator.step`` through a module-level ``jax.jit``
(``twinrl.physics.sim._step``). Inside an outer trace that is a call whose jaxpr JAX keeps (per
shapes and static arguments) with its JVP, transpose and batched forms, so the second function
that steps a scene does not trace the step again. The baseline inlines the step (our module's
``_step`` swapped for the plain function for that measurement only; nothing of ``jax`` or
``mujoco`` is touched). Each setting runs in its own process, so neither finds the other's
traces cached.

Per task, ``make_jaxpr`` seconds of, in order, in one process: an episode's return (``--horizon``
control steps from ``env.reset``), its gradient w.r.t. the actions, that gradient vmapped over
``--batch`` starts, and a second, different vmapped gradient (twice the return: a new function,
as a new test, fit or training script makes). Trace only: compile times are the persistent
cache's business and are not changed by this.

``--camera-tasks`` (arm tasks): ``make_jaxpr`` seconds of the camera choice's ascent
(``select_camera``: soft renders of one state from ``--restarts`` poses, their gradient, the hard
renders) of an untrained image actor and Q, in order: the first, a second function (same task
instance), and a third on a new instance of the same task (a test's or a loop's own ``make``).
The baseline inlines ``mjx.kinematics`` into every render (``Geoms.from_mjx``) and compares
renderers by identity (our ``Renderer``'s ``__eq__``/``__hash__`` swapped back for ``object``'s,
in that child process only).

    python bench/trace_reuse.py --out bench/results
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

STEPS = ("episode", "gradient", "vmapped gradient", "second vmapped gradient")
CAMERA = ("first ascent", "second ascent", "ascent, new task instance")


def _measure(task: str, horizon: int, batch: int, inline: bool) -> dict:
    import jax
    import jax.numpy as jnp

    from twinrl import envs
    from twinrl.physics import integrator, sim

    if inline:
        sim._step = integrator.step
    env = envs.make(task)
    s0 = env.reset(jax.random.PRNGKey(0))
    S = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), batch))
    A = jnp.zeros((horizon, env.action_size))
    AB = jnp.zeros((batch, horizon, env.action_size))

    def ret(s, a):
        return env.unroll(s, a)[1].sum()

    fns = [(ret, (s0, A)), (jax.grad(ret, 1), (s0, A)), (jax.vmap(jax.grad(ret, 1)), (S, AB)),
           (jax.vmap(jax.grad(lambda s, a: 2.0 * ret(s, a), 1)), (S, AB))]
    out = {}
    for name, (f, args) in zip(STEPS, fns):
        t0 = time.perf_counter()
        jax.make_jaxpr(f)(*args)
        out[name] = time.perf_counter() - t0
    return out


def _measure_camera(task: str, size: int, restarts: int, inline: bool) -> dict:
    import jax

    from twinrl import envs
    from twinrl.learn import sensing
    from twinrl.learn.networks import NetworkConfig, make_network
    from twinrl.render import renderer, scene

    if inline:
        from mujoco import mjx

        scene.jitted_kinematics = lambda: mjx.kinematics
        renderer.Renderer.__eq__ = object.__eq__
        renderer.Renderer.__hash__ = object.__hash__
    env = envs.make(task)
    actor = make_network({"state": (14,), "pixels/mount": (size, size, 5)}, env.action_size,
                         NetworkConfig(hidden=(16,), output="tanh"))
    cfg = sensing.SensingConfig(hidden=(16,), restarts=restarts, ascent_steps=3)
    q = sensing.make_q(actor, env.action_size, cfg)
    ap, qp = actor.init(jax.random.PRNGKey(0)), q.init(jax.random.PRNGKey(1))
    out = {}
    for name, e in zip(CAMERA, (env, env, envs.make(task))):
        s = e.reset(jax.random.PRNGKey(0))
        t0 = time.perf_counter()
        jax.make_jaxpr(lambda s, k, e=e: sensing.select_camera(e, q, qp, actor, ap, s, k, cfg))(
            s, jax.random.PRNGKey(2))
        out[name] = time.perf_counter() - t0
    return out


def _child(args, *what: str) -> dict:
    r = subprocess.run([sys.executable, __file__, "--child", *what, "--horizon",
                        str(args.horizon), "--batch", str(args.batch), "--size", str(args.size),
                        "--restarts", str(args.restarts)], capture_output=True, text=True,
                       check=True, env={**os.environ, "TWINRL_CACHE_DIR": "off"})
    return json.loads(r.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="*", default=["push", "peg_insertion", "spatula_flipping"])
    p.add_argument("--horizon", type=int, default=8)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--camera-tasks", nargs="*", default=["peg_insertion", "needle_threading"])
    p.add_argument("--size", type=int, default=16, help="the camera ascent's image size")
    p.add_argument("--restarts", type=int, default=2, help="the camera ascent's starts")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    p.add_argument("--child", nargs=3, metavar=("KIND", "TASK", "MODE"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if min(args.horizon, args.batch, args.size, args.restarts) < 1:
        p.error("--horizon, --batch, --size and --restarts must be >= 1")
    if args.child:
        kind, task, mode = args.child
        if kind == "camera":
            r = _measure_camera(task, args.size, args.restarts, mode == "inlined")
        else:
            r = _measure(task, args.horizon, args.batch, mode == "inlined")
        print(json.dumps(r))
        return 0

    from twinrl import envs
    from twinrl.report import print_table, write_json

    unknown = set(args.tasks + args.camera_tasks) - set(envs.names())
    if unknown:
        p.error(f"unknown task(s) {sorted(unknown)}; registered: {', '.join(envs.names())}")
    no_mount = [t for t in args.camera_tasks if getattr(envs.make(t), "mount", None) is None]
    if no_mount:
        p.error(f"--camera-tasks {no_mount} have no camera mount (the arm tasks do)")
    rows, camera = [], []
    for kind, tasks, out in (("step", args.tasks, rows), ("camera", args.camera_tasks, camera)):
        for task in tasks:
            out.append({"task": task, **{m: _child(args, kind, task, m)
                                         for m in ("inlined", "jitted")}})
            print(f"{task} ({kind}): done", file=sys.stderr)

    def table(title, cols, rs):
        print_table(title, ["task", *cols, "total"],
                    [[r["task"], *[f"{r['inlined'][k]:.2f} -> {r['jitted'][k]:.2f}" for k in cols],
                      f"{sum(r['inlined'].values()):.1f} -> {sum(r['jitted'].values()):.1f}"]
                     for r in rs])

    if rows:
        table(f"make_jaxpr seconds, T={args.horizon}, batch {args.batch} (inlined -> jitted)",
              STEPS, rows)
    if camera:
        table(f"make_jaxpr seconds of select_camera, {args.size}x{args.size}, {args.restarts} "
              "starts (kinematics inlined, renderers by identity -> jitted, by content)",
              CAMERA, camera)
    import jax
    import mujoco

    import twinrl
    meta = {"jax": jax.__version__, "mujoco": mujoco.__version__, "twinrl": twinrl.__version__,
            "cpu_count": os.cpu_count(), "horizon": args.horizon, "batch": args.batch,
            "size": args.size, "restarts": args.restarts}
    path = write_json(args.out / "trace_reuse.json",
                      {"meta": meta, "tasks": rows, "camera": camera})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
