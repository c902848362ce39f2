"""Large models' gradient checks: wall clock and where it goes, per model.

The Control Suite's models with at least 20 joints (from the installed ``dm_control`` package's
own XML): ``twinrl gradcheck FILE --x64 --horizon 20`` in a fresh process each, the persistent
compilation cache off (``TWINRL_CACHE_DIR=off``: a user's first run), with the stage times the
check records (``GradcheckResult.timings``: trace, compile, gradient, noise, differences) and
the process's peak memory. ``--flags MODEL=ARGS`` adds arguments for one model, e.g. MJX's
contact bound for the dog (``dog=--max-contact-points 64``), which is then measured as its own row
beside the plain one.

    python bench/gradcheck_large.py --out bench/results
    python bench/gradcheck_large.py --models humanoid stacker --flags "dog=--max-contact-points 64"
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchio import ROOT, write_result  # noqa: E402  (bench/benchio.py: the results' common meta)

MODELS = ("humanoid", "stacker", "humanoid_CMU", "dog")
"""The Control Suite's models with >= 20 joints, smallest first."""


def suite_dir() -> Path:
    import dm_control

    return Path(dm_control.__file__).parent / "suite"


def _peak_gb(pid: int) -> float:
    """``VmHWM`` (peak resident set) of a live process, in GB; 0 once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1e6
    except OSError:
        pass
    return 0.0


def check(model: str, flags: list[str], horizon: int, timeout: float) -> dict:
    """One model's check in a fresh process: its summary's verdict and timings, wall clock and
    peak memory (or how it ended when it did not finish)."""
    path = suite_dir() / f"{model}.xml"
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "twinrl.cli", "gradcheck", str(path), "--x64",
               "--horizon", str(horizon), "--out", tmp, *flags]
        env = dict(os.environ, TWINRL_CACHE_DIR="off")
        t0 = time.perf_counter()
        log, err = Path(tmp) / "stdout", Path(tmp) / "stderr"
        with open(log, "w") as o, open(err, "w") as e:  # files: a pipe left unread can fill
            proc = subprocess.Popen(cmd, stdout=o, stderr=e, text=True, env=env, cwd=ROOT)
        peak = 0.0
        while proc.poll() is None:  # the child's peak resident memory, read while it lives
            peak = max(peak, _peak_gb(proc.pid))
            if time.perf_counter() - t0 > timeout:
                proc.kill()
                proc.wait()
                # where it stood: its stages' seconds and the differences' pace so far
                return {"model": model, "flags": " ".join(flags), "peak_rss_gb": peak,
                        "status": f"timeout {timeout:.0f} s",
                        "progress_lines": [ln.strip() for ln in log.read_text().splitlines()
                                           if " s] " in ln]}
            time.sleep(1.0)
        stdout, stderr = log.read_text(), err.read_text()
        wall = time.perf_counter() - t0
        row = {"model": model, "flags": " ".join(flags), "wall_s": wall,
               "peak_rss_gb": peak, "returncode": proc.returncode}
        summary = Path(tmp) / "summary.json"
        if not summary.exists():
            return row | {"status": "no result: " + (stderr.strip().splitlines() or
                                                     ["?"])[-1][:200]}
        s = json.loads(summary.read_text())
    first = next((ln for ln in stdout.splitlines() if "[" in ln and " s] " in ln), "")
    return row | {"status": "PASS" if s["passed"] else "FAIL", "entries": s["entries"],
                  "resolved": s["resolved"], "max_rel_error": s["max_rel_error"],
                  "nan_count": s["nan_count"], "timings": s.get("timings", {}),
                  "first_progress_line": first.strip()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--models", nargs="+", default=list(MODELS))
    p.add_argument("--flags", nargs="*", default=[], metavar="MODEL=ARGS",
                   help="extra gradcheck arguments for one model, measured as an extra row")
    p.add_argument("--horizon", type=int, default=20)
    p.add_argument("--timeout", type=float, default=3600.0, help="seconds per model")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    runs = [(m, []) for m in args.models]
    for f in args.flags:
        model, _, extra = f.partition("=")
        runs.append((model, shlex.split(extra)))
    rows = []
    for model, flags in runs:
        print(f"{model} {' '.join(flags)}...", flush=True)
        rows.append(check(model, flags, args.horizon, args.timeout))
        write_result(args.out / "gradcheck_large.json", {"horizon": args.horizon, "rows": rows},
                     args)
    from twinrl.report import print_table

    print_table(f"gradcheck --x64 --horizon {args.horizon}, cold compilation cache",
                ["model", "flags", "result", "wall s", "trace", "compile", "gradient",
                 "differences", "rollouts", "peak GB"],
                [[r["model"], r["flags"], r.get("status"), r.get("wall_s"),
                  *(r.get("timings", {}).get(k) for k in ("trace", "compile", "gradient",
                                                           "differences", "rollouts")),
                  r.get("peak_rss_gb")] for r in rows])
    return 0


if __name__ == "__main__":
    sys.exit(main())
