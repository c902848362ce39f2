"""Trace and compile cost: ``twinrl.physics.smooth``'s tree stages against stock ``mjx``'s, and an
episode gradient of the manipulation tasks with each.

Every new function that differentiates a physics step pays JAX's trace (Python, per jaxpr
equation) and XLA's compile; the persistent compilation cache saves only the compile, so tests,
fits and training scripts pay the trace on every run. Two tables:

1. per model and stage (kinematics, ``com_pos``, ``crb``, ``com_vel``, ``rne``,
   ``fwd_velocity``): jaxpr equations and ``make_jaxpr`` seconds of the stage and of the
   gradient of a scalar of its outputs, stock and ours;
2. per task: ``jax.jit(jax.value_and_grad(episode return))`` over ``--horizon`` control steps from
   ``env.reset``: lower (trace) seconds, compile seconds, run seconds, with our stages and (a
   baseline measured in the same process) with stock's in their place. The baseline swaps the
   stage functions ``twinrl.physics.collision`` and ``twinrl.physics.solver`` call for stock's
   for the duration of that measurement only (our own modules; nothing of ``mujoco`` is touched).

The persistent compilation cache is off here, so every compile is a real one.

    python bench/trace.py --out bench/results
    python bench/trace.py --tasks peg_insertion --models peg_insertion push --horizon 30
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
import types
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, _jaxconfig)
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
from mujoco.mjx._src import forward as stock_forward
from mujoco.mjx._src import smooth as stock

from twinrl import envs
from twinrl.physics import collision, smooth, solver
from twinrl.report import print_table, write_json

STAGES = {
    "kinematics": (stock.kinematics, smooth.kinematics),
    "com_pos": (stock.com_pos, smooth.com_pos),
    "crb": (stock.crb, smooth.crb),
    "com_vel": (stock.com_vel, smooth.com_vel),
    "rne": (stock.rne, smooth.rne),
    "fwd_velocity": (stock_forward.fwd_velocity, smooth.fwd_velocity),
}
STOCK = types.SimpleNamespace(kinematics=stock.kinematics, com_pos=stock.com_pos, crb=stock.crb,
                              fwd_velocity=stock_forward.fwd_velocity)


def _eqns(jaxpr) -> int:
    n = 0
    for e in jaxpr.eqns:
        n += 1
        for p in e.params.values():
            inner = getattr(p, "jaxpr", None)
            if inner is not None:
                n += _eqns(getattr(inner, "jaxpr", inner))
    return n


def _trace(fn, *args) -> tuple[int, float]:
    t0 = time.perf_counter()
    j = jax.make_jaxpr(fn)(*args)
    return _eqns(j.jaxpr), time.perf_counter() - t0


def bench_stages(name: str) -> list[dict]:
    mj = envs.make(name).sim.mj_model
    m = mjx.put_model(mj)
    rng = np.random.default_rng(0)
    d = mjx.make_data(m).replace(qpos=jnp.asarray(mj.qpos0 + rng.normal(0, 0.3, mj.nq),
                                                  jnp.float32))
    d = jax.jit(mjx.forward)(m, d)
    leaves, treedef = jax.tree_util.tree_flatten(d)
    floats = [i for i, x in enumerate(leaves) if jnp.issubdtype(x.dtype, jnp.floating)]

    def data(xs):  # the Data with its floating-point leaves replaced by xs
        new = list(leaves)
        for i, x in zip(floats, xs):
            new[i] = x
        return jax.tree_util.tree_unflatten(treedef, new)

    xs = [leaves[i] for i in floats]
    rows = []
    for stage, fns in STAGES.items():
        row = {"model": name, "stage": stage, "nbody": int(mj.nbody)}
        for label, fn in zip(("stock", "ours"), fns):
            def out(xs, fn=fn):
                return fn(m, data(xs))

            def scalar(xs, out=out):  # a gradient w.r.t. everything the stage reads
                ys = [y for y in jax.tree_util.tree_leaves(out(xs))
                      if jnp.issubdtype(y.dtype, jnp.floating)]
                return sum(jnp.sum(jnp.sin(y)) for y in ys)

            row[f"{label}_eqns"], row[f"{label}_trace_s"] = _trace(out, xs)
            row[f"{label}_grad_eqns"], row[f"{label}_grad_trace_s"] = _trace(
                jax.grad(scalar), xs)
        rows.append(row)
    return rows


@contextlib.contextmanager
def _stock_stages():
    saved = collision._tree, solver._tree
    collision._tree = solver._tree = STOCK
    try:
        yield
    finally:
        collision._tree, solver._tree = saved


def bench_episode(name: str, horizon: int) -> dict:
    env = envs.make(name)

    def ret(actions, key):
        def body(s, a):
            s = env.step(s, a)
            return s, s.reward
        return jnp.sum(jax.lax.scan(body, env.reset(key), actions)[1])

    a = jnp.zeros((horizon, env.action_size), jnp.float32)
    key = jax.random.PRNGKey(0)
    row: dict = {"task": name, "horizon": horizon}
    for label, ctx in (("stock", _stock_stages), ("ours", contextlib.nullcontext)):
        with ctx():
            f = jax.jit(jax.value_and_grad(ret))
            t0 = time.perf_counter()
            lowered = f.lower(a, key)
            t1 = time.perf_counter()
            compiled = lowered.compile()
            t2 = time.perf_counter()
            value, grad = jax.block_until_ready(compiled(a, key))
            t3 = time.perf_counter()
            jax.block_until_ready(compiled(a, key))
            t4 = time.perf_counter()
        row.update({f"{label}_lower_s": t1 - t0, f"{label}_compile_s": t2 - t1,
                    f"{label}_run_s": t4 - t3, f"{label}_value": float(value),
                    f"{label}_grad_norm": float(jnp.linalg.norm(grad))})
        print(f"[bench] {name} {label}: lower {t1 - t0:.1f} s, compile {t2 - t1:.1f} s, "
              f"run {t4 - t3:.3f} s", flush=True)
    return row


def _rel(a: float, b: float) -> float:
    return abs(a - b) / max(abs(a), 1e-30)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="*", default=["peg_insertion", "spatula_flipping", "push",
                                                   "cartpole_swingup"], choices=envs.names())
    p.add_argument("--tasks", nargs="*", default=["peg_insertion", "spatula_flipping",
                                                  "needle_threading"], choices=envs.names())
    p.add_argument("--horizon", type=int, default=30)
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    if args.horizon < 1:
        p.error(f"--horizon must be >= 1, got {args.horizon}")
    jax.config.update("jax_enable_compilation_cache", False)
    stages = [r for name in args.models for r in bench_stages(name)]
    print_table("tree stages: jaxpr equations and trace seconds (stock -> ours)",
                ["model", "stage", "eqns", "trace s", "grad eqns", "grad trace s"],
                [[r["model"], r["stage"], f"{r['stock_eqns']} -> {r['ours_eqns']}",
                  f"{r['stock_trace_s']:.2f} -> {r['ours_trace_s']:.2f}",
                  f"{r['stock_grad_eqns']} -> {r['ours_grad_eqns']}",
                  f"{r['stock_grad_trace_s']:.2f} -> {r['ours_grad_trace_s']:.2f}"]
                 for r in stages])
    episodes = [bench_episode(name, args.horizon) for name in args.tasks]
    print_table(f"episode value_and_grad, T={args.horizon} (stock stages -> ours), seconds",
                ["task", "lower", "compile", "run", "|value diff|", "grad norm rel diff"],
                [[r["task"], f"{r['stock_lower_s']:.1f} -> {r['ours_lower_s']:.1f}",
                  f"{r['stock_compile_s']:.1f} -> {r['ours_compile_s']:.1f}",
                  f"{r['stock_run_s']:.3f} -> {r['ours_run_s']:.3f}",
                  f"{abs(r['stock_value'] - r['ours_value']):.1e}",
                  f"{_rel(r['stock_grad_norm'], r['ours_grad_norm']):.1e}"]
                 for r in episodes])
    meta = {"jax": jax.__version__, "mujoco": mujoco.__version__, "twinrl": twinrl.__version__,
            "device": str(jax.devices()[0]), "cpu_count": __import__("os").cpu_count()}
    path = write_json(args.out / "trace.json", {"meta": meta, "stages": stages,
                                                "episodes": episodes})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
