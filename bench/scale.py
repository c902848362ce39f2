"""Scaling benchmark: the same training on 1 and 2 processes (``jax.distributed``), a core each.

For each algorithm (``shac``: one global batch sharded over the processes' devices,
``twinrl.learn.distributed``; ``ppo``: Brax PPO's own multi-process path, each process stepping
``num_envs / processes`` environments and the gradients averaged over all devices) and each
process count in ``--processes``, the processes are started on 127.0.0.1 (JAX's Gloo CPU
collectives), each pinned to its own core with ``taskset`` and to one XLA thread. Reported per run:

- ``env_steps_per_s``: training environment steps per second of wall clock between the first
  progress report (which holds the compilation) and the last (evaluations included), and the
  wall clock of the whole run (compile included);
- ``wall_s_to_target``: the wall clock (compile included) at which the evaluation return first
  reached ``--target`` (None: not within the run);
- the final return.

The global batch is the same at every process count (SHAC: ``num_envs`` environments in all),
so the speed-up is the step rate's ratio; SHAC's runs learn the same policy up to float
reduction order (``tests/learn/test_distributed.py``), PPO's draw per-process random streams.
A table is printed and ``scale.json`` written to ``--out``::

    python bench/scale.py --out bench/results                        # SHAC and PPO, 1 and 2
    python bench/scale.py --algos shac --shac-epochs 30 --shac-envs 64 --out /tmp/scale  # short

``--widths 256 1024 ...`` runs one process at those environment counts instead (a GPU machine:
how the step rate grows with the batch on one device).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

from benchio import ROOT, write_result  # noqa: E402  (bench/benchio.py: the results' common meta)

ALGOS = ("shac", "ppo")
ONE_THREAD = ("--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1 "
              "--xla_cpu_use_fusion_emitters=false")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def overrides(args, algo: str, width: int | None) -> dict:
    """The run's config overrides (the CLI's tuned config otherwise)."""
    if algo == "shac":
        return {"epochs": args.shac_epochs, "num_envs": width or args.shac_envs}
    return {"num_timesteps": args.ppo_steps, "num_envs": width or args.ppo_envs,
            "num_evals": args.ppo_evals}


def worker(args) -> int:
    """One process of a run: train, record the progress reports, process 0 writes them."""
    from twinrl.learn import distributed

    if args.processes > 1:  # before anything starts a JAX backend
        distributed.initialize(args.coordinator, args.processes, args.process_id,
                               timeout_s=600, heartbeat_s=600)
    import jax

    from twinrl import envs
    from twinrl.learn import runner

    config = runner.make_config(args.algo, args.env, json.loads(args.overrides))
    _, train, _ = runner.algorithm(args.algo)
    env = envs.make(args.env)
    rows, t0 = [], time.perf_counter()

    def progress(_, row):
        rows.append({"wall_s": time.perf_counter() - t0, "env_steps": float(row["env_steps"]),
                     "return": float(row["return"])})

    with distributed.guard("bench/scale.py"):
        train(env, config, jax.random.key(args.seed), progress_fn=progress)
    if distributed.is_writer():
        Path(args.record).write_text(json.dumps({"rows": rows, "wall_s": time.perf_counter() - t0,
                                                 "devices": len(jax.devices())}))
    return 0


def launch(args, algo: str, processes: int, width: int | None, out: Path) -> dict:
    """Start one run's processes (pinned to cores 0 .. processes - 1) and summarise it."""
    record = out / f"scale_runs/{algo}-{processes}p-{width or 'default'}.json"
    record.parent.mkdir(parents=True, exist_ok=True)
    port = _free_port()
    env = dict(os.environ, XLA_FLAGS=ONE_THREAD,
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cores = os.cpu_count() or 1
    procs = []
    for i in range(processes):
        cmd = [sys.executable, __file__, "--worker", "--algo", algo, "--env", args.env,
               "--seed", str(args.seed), "--processes", str(processes), "--process-id", str(i),
               "--coordinator", f"127.0.0.1:{port}", "--record", str(record),
               "--overrides", json.dumps(overrides(args, algo, width))]
        if processes <= cores:
            cmd = ["taskset", "-c", str(i), *cmd]
        procs.append(subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, text=True))
    errors = [p.communicate()[1] for p in procs]
    failed = [(p.returncode, e.strip().splitlines()[-1:] or [""]) for p, e in zip(procs, errors)
              if p.returncode]
    if failed:
        return {"algo": algo, "processes": processes, "width": width, "error": failed[0][1][0],
                "exit": failed[0][0]}
    run = json.loads(record.read_text())
    rows = run["rows"]
    steady = rows[1:] if len(rows) > 1 else rows
    rate = ((steady[-1]["env_steps"] - rows[0]["env_steps"])
            / max(steady[-1]["wall_s"] - rows[0]["wall_s"], 1e-9)) if len(rows) > 1 else None
    hit = next((r["wall_s"] for r in rows if r["return"] >= args.target), None)
    return {"algo": algo, "processes": processes, "devices": run["devices"],
            "width": width or overrides(args, algo, None)["num_envs"],
            "env_steps": rows[-1]["env_steps"], "env_steps_per_s": rate,
            "first_report_s": rows[0]["wall_s"], "wall_s": run["wall_s"],
            "wall_s_to_target": hit, "final_return": rows[-1]["return"],
            "best_return": max(r["return"] for r in rows), "reports": len(rows)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--algos", nargs="+", choices=ALGOS, default=list(ALGOS))
    p.add_argument("--env", default="cartpole_swingup")
    p.add_argument("--processes", nargs="+", type=int, default=[1, 2])
    p.add_argument("--widths", nargs="+", type=int, default=None,
                   help="one process at these environment counts instead (a GPU machine)")
    p.add_argument("--shac-epochs", type=int, default=150)
    p.add_argument("--shac-envs", type=int, default=256)
    p.add_argument("--ppo-steps", type=int, default=300_000)
    p.add_argument("--ppo-envs", type=int, default=256)
    p.add_argument("--ppo-evals", type=int, default=6)
    p.add_argument("--target", type=float, default=80.0,
                   help="the return whose first reaching is timed (default 80)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    # one worker process (launch's)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--algo", help=argparse.SUPPRESS)
    p.add_argument("--process-id", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--coordinator", help=argparse.SUPPRESS)
    p.add_argument("--record", help=argparse.SUPPRESS)
    p.add_argument("--overrides", default="{}", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        args.processes = args.processes[0]
        return worker(args)

    from twinrl.report import print_table

    args.out.mkdir(parents=True, exist_ok=True)
    plan = ([(a, 1, w) for a in args.algos for w in args.widths] if args.widths else
            [(a, n, None) for a in args.algos for n in args.processes])
    runs = []
    for algo, n, width in plan:
        runs.append(launch(args, algo, n, width, args.out))
        r = runs[-1]
        print(f"{algo} x{n} ({r.get('width')} envs): "
              + (f"error: {r['error']}" if "error" in r else
                 f"{r['env_steps_per_s']:.0f} steps/s, {r['wall_s']:.0f} s"), flush=True)
    for r in runs:  # speed-up against the same algorithm's one-process run
        base = next((b for b in runs if b["algo"] == r["algo"] and b["processes"] == 1
                     and b.get("width") == r.get("width") and b.get("env_steps_per_s")), None)
        if base and r.get("env_steps_per_s"):
            r["speedup"] = r["env_steps_per_s"] / base["env_steps_per_s"]

    def fmt(x, spec=".0f"):
        return "-" if x is None else format(x, spec)

    print_table(f"{args.env}: 1 core per process (target return {args.target:g})",
                ["algo", "processes", "envs", "env steps/s", "speed-up", "wall s",
                 "s to target", "final return"],
                [[r["algo"], r["processes"], r.get("width"),
                  fmt(r.get("env_steps_per_s")), fmt(r.get("speedup"), ".2f"),
                  fmt(r.get("wall_s")), fmt(r.get("wall_s_to_target")),
                  fmt(r.get("final_return"), ".1f")] if "error" not in r else
                 [r["algo"], r["processes"], r.get("width"), "error", r["error"][:60], "", "", ""]
                 for r in runs])
    path = write_result(args.out / "scale.json", {"env": args.env, "target": args.target,
                                                  "runs": runs}, args)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
