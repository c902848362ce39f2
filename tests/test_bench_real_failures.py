"""``bench/real_failures.py``'s grouping of a loop's real starts: the figures of the starts the
actor failed in the real twin against those it solved, each over the starts that measured it."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

GROUPS = """
import json, sys
from real_failures import groups
print(json.dumps(groups(json.loads(sys.argv[1]))))
"""


def _groups(starts):
    r = subprocess.run([sys.executable, "-c", GROUPS, json.dumps(starts)], cwd=ROOT,
                       capture_output=True, text=True,
                       env={"PYTHONPATH": f"{ROOT}:{ROOT / 'bench'}", "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr[-2000:]
    return {g["group"]: g for g in json.loads(r.stdout.strip().splitlines()[-1])}


def test_failed_and_solved_starts_are_summarised_apart():
    end = lambda xy, z: {"xy": xy, "z": z}  # noqa: E731
    starts = [
        # two real failures: the twin's actor fails both, the real actions fail in the twin once;
        # the plans (only these were planned) solve both in the twin and one in real
        {"real": False, "sim_actor": False, "replay": False, "real_end": end(3.0, -10.0),
         "plan_sim": True, "plan_real": True},
        {"real": False, "sim_actor": False, "replay": True, "real_end": end(5.0, -20.0),
         "plan_sim": True, "plan_real": False},
        # three solved, one planned as a control; one without a tool end (None: not measured)
        {"real": True, "sim_actor": True, "replay": True, "real_end": end(1.0, -38.0),
         "plan_sim": True, "plan_real": True},
        {"real": True, "sim_actor": False, "replay": True, "real_end": end(2.0, -36.0)},
        {"real": True, "sim_actor": True, "replay": True, "real_end": None},
    ]
    g = _groups(starts)
    f, s = g["failed"], g["solved"]
    assert (f["starts"], f["sim_actor"], f["replay"]) == (2, 0.0, 0.5)
    assert (f["plan_sim"], f["plan_real"], f["plan_real_n"]) == (1.0, 0.5, 2)
    assert (f["real_end_xy_mm"], f["real_end_z_mm"]) == (4.0, -15.0)  # medians
    assert (s["starts"], s["sim_actor"], s["replay"]) == (3, 2 / 3, 1.0)
    assert (s["plan_sim"], s["plan_real"], s["plan_real_n"]) == (1.0, 1.0, 1)
    assert (s["real_end_xy_mm"], s["real_end_z_mm"]) == (1.5, -37.0)
    assert f["sim_truth"] is None and f["sim_truth_n"] == 0  # a target-cloud actor has no pose


def test_bad_arguments_exit_with_one_line():
    r = subprocess.run([sys.executable, "bench/real_failures.py", "--run", "nope=/nowhere"],
                       cwd=ROOT, capture_output=True, text=True,
                       env={"PYTHONPATH": f"{ROOT}:{ROOT / 'bench'}", "PATH": "/usr/bin:/bin"})
    assert r.returncode != 0 and "TASK=DIR" in r.stderr.strip().splitlines()[-1]
