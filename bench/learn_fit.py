"""The learners' minibatch fit (``twinrl.learn.common.make_minibatch_fit``): run time per Adam
step with every step inside one compiled ``lax.scan`` against one compiled step called per step.

XLA's CPU backend runs a convolution's gradient inside a loop body far slower than at the top
level (jax-ml/jax#12868), so ``loop="auto"`` calls one step at a time where the observations hold
images and keeps the scan for vectors (where a call's dispatch is most of a step). Cases:
- ``pixels``: the image actor's fit (``ImitationConfig(observation="pixels")``'s spec on an arm
  task: proprioception, a 64x64 RGB-D + segmentation image, the commanded camera; the keypoint
  CNN, strides 2, 2, 1; hidden 256, 256; batch 256; RGB jitter);
- ``state``: the same fit on a state vector (the state actor's: 40 inputs, hidden 256, 256).

Random data (the fit's cost does not depend on it); compile seconds are the first call's. The
first call of ``scan`` also runs its steps, so its compile column is the first call less the
run.

    python bench/learn_fit.py --out bench/results
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import twinrl  # noqa: F401  (before any JAX work: twinrl's XLA settings)
from twinrl.learn.common import make_minibatch_fit, make_optimizer, rgb_jitter
from twinrl.learn.networks import NetworkConfig, make_network
from twinrl.report import print_table, run_meta, write_json

SPECS = {"pixels": {"state": (14,), "pixels/mount": (64, 64, 5), "camera": (3,)},
         "state": 40}


def case(name: str, loop: str, steps: int, batch: int, rows: int = 2048) -> dict:
    spec = SPECS[name]
    net = make_network(spec, 7, NetworkConfig(hidden=(256, 256), activation="elu",
                                              output="tanh", image_head="keypoints",
                                              conv_strides=(2, 2, 1)))
    params = net.init(jax.random.key(0))
    rng = np.random.default_rng(0)
    if isinstance(spec, int):
        obs = jnp.asarray(rng.normal(size=(rows, spec)), jnp.float32)
    else:
        obs = {k: jnp.asarray(rng.uniform(size=(rows,) + v), jnp.float32)
               for k, v in spec.items()}
    targets = jnp.asarray(rng.uniform(-1, 1, size=(rows, 7)), jnp.float32)
    tx = make_optimizer(3e-4, 1.0)
    fit = make_minibatch_fit(net.apply, tx, steps, batch,
                             rgb_jitter(0.1) if name == "pixels" else None, loop=loop)
    t0 = time.perf_counter()
    jax.block_until_ready(fit(params, tx.init(params), obs, targets, rows, jax.random.key(1)))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = jax.block_until_ready(fit(params, tx.init(params), obs, targets, rows,
                                    jax.random.key(2)))
    run = time.perf_counter() - t0
    return {"case": name, "loop": loop, "steps": steps, "batch": batch,
            "ms_per_step": 1e3 * run / steps, "compile_s": max(first - run, 0.0),
            "final_loss": float(out[2][-1]), "auto": fit.loop_for(obs) if loop == "auto" else None}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", nargs="*", default=list(SPECS), choices=list(SPECS))
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--steps", type=int, nargs=2, default=[5, 20], metavar=("SCAN", "PYTHON"),
                   help="steps timed per image fit: inside the scan (seconds each), called one "
                        "by one; vector fits run 100 either way")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    if args.batch < 1 or min(args.steps) < 1:
        p.error("--batch and --steps must be >= 1")
    jax.config.update("jax_enable_compilation_cache", False)
    rows = []
    for name in args.cases:
        for loop in ("scan", "python"):
            steps = ((args.steps[0] if loop == "scan" else args.steps[1]) if name == "pixels"
                     else 100)
            rows.append(case(name, loop, steps, args.batch))
            print(f"  {name} {loop}: {rows[-1]['ms_per_step']:.1f} ms a step", flush=True)
    ms = {(x["case"], x["loop"]): x["ms_per_step"] for x in rows}
    speed = {n: ms[n, "scan"] / ms[n, "python"] for n in args.cases}
    probe = {"pixels": {"x": jnp.zeros((1, 1, 1, 1))}, "state": jnp.zeros((1, 1))}
    chooses = make_minibatch_fit(lambda p, o: o, None, 1, 1).loop_for
    print_table(f"minibatch fit, batch {args.batch}, ms per Adam step ({os.cpu_count()} cores)",
                ["case", "scan", "one call a step", "scan / calls", "compile s (scan, calls)",
                 "auto takes"],
                [[n, f"{ms[n, 'scan']:.1f}", f"{ms[n, 'python']:.1f}", f"{speed[n]:.1f}x",
                  " / ".join(f"{x['compile_s']:.1f}" for x in rows if x["case"] == n),
                  chooses(probe[n])] for n in args.cases])
    meta = {**run_meta(args), "xla_flags": os.environ.get("XLA_FLAGS", "")}
    path = write_json(args.out / "learn_fit.json", {"meta": meta, "rows": rows,
                                                    "scan_over_calls": speed})
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
