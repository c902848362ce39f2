"""The whole loop, as ``make run`` runs it: ``twinrl run`` on a task's real twin, timed.

Runs ``twinrl run --env ENV --seed S --out DIR`` (the command's defaults: the loop's rounds,
Brax PPO in the identified simulator, the residual gate, the oracle trained on the hidden truth
for evaluation only) in a fresh process, then reads the run's ``summary.json``: the real steps it
used, the final policy's return on the real twin, the oracle's, their ratio, each parameter's
error against the hidden truth, the seconds each stage took and the wall-clock time of the whole
command (compilation included; a warm compilation cache makes it shorter).

    python bench/loop.py --out bench/results                  # cartpole_swingup, twin 0
    python bench/loop.py --env pendulum_swingup --seeds 0 1 --out /tmp/b
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchio import RESULTS, write_result


def run_loop(env: str, seed: int, out: Path) -> dict:
    """One ``twinrl run`` into ``out``; its summary's final round and the command's wall time."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "twinrl.cli", "run", "--env", env, "--seed",
                           str(seed), "--out", str(out)], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"twinrl run --env {env} --seed {seed} failed ({proc.returncode}):\n"
                         f"{proc.stderr[-2000:]}")
    final = json.loads((out / "summary.json").read_text())["final"]
    return {"env": env, "seed": seed, "wall_s": wall, "real_steps": final["real_steps"],
            "real_return": final["real_return"], "oracle_return": final["oracle_return"],
            "fraction_of_oracle": final["fraction_of_oracle"],
            "residual_accepted": final.get("residual_accepted"),
            "largest_param_error": max(final["param_rel_error"].values()),
            "param_rel_error": final["param_rel_error"], "seconds": final["seconds"]}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--env", default="cartpole_swingup", help="task (default: make run's)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="real-twin seeds")
    p.add_argument("--out", type=Path, default=RESULTS, help="directory of loop.json")
    args = p.parse_args(argv)
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            print(f"twinrl run --env {args.env} --seed {seed} ...", flush=True)
            r = run_loop(args.env, seed, Path(tmp) / f"seed{seed}")
            print(f"  {100 * r['fraction_of_oracle']:.1f} % of the oracle from "
                  f"{r['real_steps']:,} real steps in {r['wall_s']:.0f} s", flush=True)
            runs.append(r)
    path = write_result(args.out / "loop.json", {"runs": runs}, args)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
