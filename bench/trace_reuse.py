"""Trace reuse of the physics step: ``Sim.step`` through one jitted function against the step
inlined into every function that takes it.

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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="*", default=["push", "peg_insertion", "spatula_flipping"])
    p.add_argument("--horizon", type=int, default=8)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    p.add_argument("--child", nargs=2, metavar=("TASK", "MODE"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.horizon < 1 or args.batch < 1:
        p.error("--horizon and --batch must be >= 1")
    if args.child:
        task, mode = args.child
        print(json.dumps(_measure(task, args.horizon, args.batch, mode == "inlined")))
        return 0

    from twinrl import envs
    from twinrl.report import print_table, write_json

    unknown = set(args.tasks) - set(envs.names())
    if unknown:
        p.error(f"unknown task(s) {sorted(unknown)}; registered: {', '.join(envs.names())}")
    rows = []
    for task in args.tasks:
        row = {"task": task}
        for mode in ("inlined", "jitted"):
            r = subprocess.run([sys.executable, __file__, "--child", task, mode,
                                "--horizon", str(args.horizon), "--batch", str(args.batch)],
                               capture_output=True, text=True, check=True,
                               env={**os.environ, "TWINRL_CACHE_DIR": "off"})
            row[mode] = json.loads(r.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(f"{task}: done", file=sys.stderr)
    print_table(f"make_jaxpr seconds, T={args.horizon}, batch {args.batch} (inlined -> jitted)",
                ["task", *STEPS, "total"],
                [[r["task"], *[f"{r['inlined'][k]:.2f} -> {r['jitted'][k]:.2f}" for k in STEPS],
                  f"{sum(r['inlined'].values()):.1f} -> {sum(r['jitted'].values()):.1f}"]
                 for r in rows])
    import jax
    import mujoco

    import twinrl
    meta = {"jax": jax.__version__, "mujoco": mujoco.__version__, "twinrl": twinrl.__version__,
            "cpu_count": os.cpu_count(), "horizon": args.horizon, "batch": args.batch}
    path = write_json(args.out / "trace_reuse.json", {"meta": meta, "tasks": rows})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
