"""Kill `twinrl collect` with SIGKILL at random moments; the dataset must stay readable and whole.

Each round starts ``twinrl collect`` appending to the same dataset, kills it with SIGKILL after a
random delay (seeded), then reads the dataset in strict mode and checks: it is readable; no
transition recorded before the kill is lost (the count never decreases and the earlier
transitions are unchanged); every episode marked complete has the task's full length. Prints a
table and writes JSON.

    python bench/kill_collect.py --kills 20 --out bench/results
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from twinrl.real.dataset import read
from twinrl.report import print_table, write_json


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--kills", type=int, default=20)
    p.add_argument("--env", default="pendulum_swingup")
    p.add_argument("--min-delay", type=float, default=4.0)
    p.add_argument("--max-delay", type=float, default=14.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    work = Path(tempfile.mkdtemp(prefix="twinrl-kill-"))
    data_dir = work / "run"
    rows, prev_obs = [], None
    try:
        for k in range(args.kills):
            delay = float(rng.uniform(args.min_delay, args.max_delay))
            proc = subprocess.Popen(
                [sys.executable, "-m", "twinrl.cli", "collect", "--env", args.env,
                 "--episodes", "1000", "--seed", str(k), "--out", str(data_dir)],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                env={**os.environ, "PYTHONUNBUFFERED": "1"})
            time.sleep(delay)
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            if not (data_dir / "dataset").exists():
                rows.append({"kill": k, "delay_s": delay, "recorded": 0, "readable": True,
                             "lost": 0, "complete_episodes_full": True, "note": "before start"})
                continue
            ds = read(data_dir / "dataset", strict=True)  # raises if unreadable
            n = len(ds)
            lost = 0
            if prev_obs is not None:
                lost = max(0, len(prev_obs) - n)
                same = n >= len(prev_obs) and np.array_equal(ds.obs[:len(prev_obs)], prev_obs)
                lost += 0 if same else 1
            lengths = ds.episode_ends - ds.episode_starts
            full = bool(np.all(lengths[ds.episode_complete] == lengths[ds.episode_complete].max()))
            rows.append({"kill": k, "delay_s": delay, "recorded": n, "readable": True,
                         "lost": lost, "episodes": int(ds.num_episodes),
                         "complete_episodes_full": full,
                         "new_this_round": n - (len(prev_obs) if prev_obs is not None else 0)})
            prev_obs = ds.obs.copy()
            print(f"kill {k:2d} after {delay:5.1f}s: {n} transitions, "
                  f"{rows[-1]['new_this_round']} new, lost {lost}", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print_table(f"SIGKILL of `twinrl collect --env {args.env}`",
                ["kill", "after s", "recorded", "new", "lost", "episodes", "complete full"],
                [[r["kill"], r["delay_s"], r["recorded"], r.get("new_this_round", 0), r["lost"],
                  r.get("episodes", 0), r["complete_episodes_full"]] for r in rows])
    summary = {"env": args.env, "kills": args.kills, "rows": rows,
               "all_readable": all(r["readable"] for r in rows),
               "total_lost": sum(r["lost"] for r in rows),
               "final_transitions": rows[-1]["recorded"] if rows else 0}
    write_json(args.out / "kill_collect.json", summary)
    print(f"lost {summary['total_lost']} transitions over {args.kills} kills; "
          f"final dataset {summary['final_transitions']} transitions")
    return 0 if summary["total_lost"] == 0 and summary["all_readable"] else 1


if __name__ == "__main__":
    sys.exit(main())
