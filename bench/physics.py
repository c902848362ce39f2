"""Physics throughput: compile time, forward and gradient env-steps/s, stock MJX and MuJoCo C.

Per bundled scene (T = 100-step open-loop rollouts, float32, CPU unless JAX finds an accelerator):
- compile seconds of the forward rollout and of its gradient;
- forward env-steps/s: single env, vmap 256 (ours); the same through stock ``mjx.step``;
- forward+backward env-steps/s of the rollout-loss gradient w.r.t. actions: single, vmap 16;
- gradient/forward cost ratio (time of value-and-gradient / time of forward, same batch);
- MuJoCo C ``mj_step`` steps/s (``mujoco.rollout``, one thread).

``--gradient implicit unrolled`` measures both derivatives of the constraint solve in one run
(``twinrl.physics.solver``: the implicit-function-theorem derivative, the default, adds one
nv x nv solve per step to the backward pass); the table then has a row per scene and mode.
``--contacts mjx mujoco`` does the same for the collision rules (``twinrl.physics.collision``:
MuJoCo C's box on a plane), ``--iterations N`` overrides the scenes' solver iterations (the
stock columns always run stock MJX's collision and the scene's iterations).

Timings are the best of ``--repeats`` calls after a warm-up call. Prints a table, writes JSON.

    python bench/physics.py --out bench/results            # all scenes
    python bench/physics.py --scenes cartpole push --repeats 5
    python bench/physics.py --scenes push --gradient implicit unrolled
    python bench/physics.py --scenes push --contacts mjx mujoco --iterations 12
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import twinrl  # noqa: F401  (before jax: XLA's cache-load log lines stay hidden, jaxconfig)
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from twinrl.physics import SCENES, Sim
from twinrl.physics.collision import CONTACTS
from twinrl.physics.scenes import scenario
from twinrl.report import print_table
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)

T = 100


def _best(fn, *args, repeats: int) -> float:
    jax.block_until_ready(fn(*args))  # warm-up (already compiled)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return min(times)


def _compile(fn, *args) -> tuple[float, object]:
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - t0, fn


def bench_scene(name: str, repeats: int, gradient: str = "implicit", contacts: str = "mjx",
                iterations: int | None = None) -> dict:
    sim = Sim.load(name, gradient=gradient, contacts=contacts, iterations=iterations)
    sc = scenario(name, sim.nq, sim.nv, sim.nu, sim.mj_model.qpos0, horizon=T)
    q0, v0 = jnp.asarray(sc.qpos, jnp.float32), jnp.asarray(sc.qvel, jnp.float32)
    acts = jnp.asarray(sc.actions, jnp.float32)

    def fwd(a, step_fn=None):
        _, tr = sim.rollout(sim.init(q0, v0), a, step_fn=step_fn)
        return jnp.sum(tr.qpos) + jnp.sum(tr.qvel)

    ours = jax.jit(fwd)
    stock = jax.jit(lambda a: fwd(a, sim.stock_step))
    grad = jax.jit(jax.value_and_grad(fwd))
    batch = lambda f: jax.jit(jax.vmap(f))
    a256, a16 = jnp.broadcast_to(acts, (256,) + acts.shape), jnp.broadcast_to(acts, (16,) + acts.shape)

    out: dict = {"scene": name, "gradient": gradient, "contacts": contacts, "T": T, "nv": sim.nv,
                 "nu": sim.nu,
                 "solver_iterations": int(sim.mj_model.opt.iterations)}
    out["compile_forward_s"], _ = _compile(ours, acts)
    out["compile_grad_s"], _ = _compile(grad, acts)
    t_fwd1 = _best(ours, acts, repeats=repeats)
    t_grad1 = _best(grad, acts, repeats=repeats)
    ours256, ours16, grad16 = batch(fwd), batch(fwd), batch(jax.value_and_grad(fwd))
    t_fwd256 = _best(ours256, a256, repeats=repeats)
    t_fwd16 = _best(ours16, a16, repeats=repeats)
    t_grad16 = _best(grad16, a16, repeats=repeats)
    stock256 = batch(lambda a: fwd(a, sim.stock_step))
    t_stock1 = _best(stock, acts, repeats=repeats)
    t_stock256 = _best(stock256, a256, repeats=repeats)

    out.update({
        "forward_steps_per_s_single": T / t_fwd1,
        "forward_steps_per_s_vmap256": 256 * T / t_fwd256,
        "grad_steps_per_s_single": T / t_grad1,
        "grad_steps_per_s_vmap16": 16 * T / t_grad16,
        "grad_forward_ratio_single": t_grad1 / t_fwd1,
        "grad_forward_ratio_vmap16": t_grad16 / t_fwd16,
        "stock_forward_steps_per_s_single": T / t_stock1,
        "stock_forward_steps_per_s_vmap256": 256 * T / t_stock256,
    })
    out["mujoco_c_steps_per_s"] = _mujoco_c(sim, sc)
    return out


def _mujoco_c(sim: Sim, sc) -> float:
    from mujoco import rollout

    m, d = sim.mj_model, mujoco.MjData(sim.mj_model)
    d.qpos[:], d.qvel[:] = sc.qpos, sc.qvel
    state = np.empty(mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_FULLPHYSICS))
    mujoco.mj_getState(m, d, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
    n = 20 * T
    ctrl = np.tile(np.asarray(sc.actions), (20, 1))[None]
    rollout.rollout(m, d, state[None], ctrl)  # warm-up
    t0 = time.perf_counter()
    rollout.rollout(m, d, state[None], ctrl)
    return n / (time.perf_counter() - t0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenes", nargs="*", default=list(SCENES), choices=SCENES)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--gradient", nargs="*", default=["implicit"], choices=("implicit", "unrolled"),
                   help="derivative(s) of the constraint solve to measure (default implicit)")
    p.add_argument("--contacts", nargs="*", default=["mjx"], choices=CONTACTS,
                   help="collision rules to measure (default mjx, stock)")
    p.add_argument("--iterations", type=int, default=None,
                   help="solver iterations (default: each scene's MJCF)")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    if args.iterations is not None and args.iterations < 1:
        p.error(f"--iterations must be >= 1, got {args.iterations}")
    rows = []
    for name in args.scenes:
        for gradient in args.gradient:
            for contacts in args.contacts:
                print(f"[bench] {name} ({gradient}, {contacts}) ...", flush=True)
                rows.append(bench_scene(name, args.repeats, gradient, contacts, args.iterations))
    print_table(f"physics throughput (env-steps/s, T={T}, {jax.devices()[0].platform})",
                ["scene", "gradient", "contacts", "iterations", "compile fwd s", "compile grad s",
                 "fwd 1", "fwd vmap256",
                 "grad 1", "grad vmap16", "grad/fwd 1", "grad/fwd 16", "stock fwd 1",
                 "stock vmap256", "MuJoCo C"],
                [[r["scene"], r["gradient"], r["contacts"], r["solver_iterations"],
                  r["compile_forward_s"], r["compile_grad_s"],
                  r["forward_steps_per_s_single"], r["forward_steps_per_s_vmap256"],
                  r["grad_steps_per_s_single"], r["grad_steps_per_s_vmap16"],
                  r["grad_forward_ratio_single"], r["grad_forward_ratio_vmap16"],
                  r["stock_forward_steps_per_s_single"], r["stock_forward_steps_per_s_vmap256"],
                  r["mujoco_c_steps_per_s"]] for r in rows])
    path = write_result(args.out / "physics.json", {"scenes": rows}, args)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
