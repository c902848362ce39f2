"""``bench/actor_views.py``'s split of an image actor's success from random views by whether
the view's fitted pose is right, and the success the other views would need."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

SPLIT = """
import json, sys
from actor_views import split
print(json.dumps([split(*json.loads(a)) for a in sys.argv[1:]]))
"""


def _split(*cases):
    r = subprocess.run([sys.executable, "-c", SPLIT, *map(json.dumps, cases)], cwd=ROOT,
                       capture_output=True, text=True,
                       env={"PYTHONPATH": f"{ROOT}:{ROOT / 'bench'}", "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_split_by_the_views_share_of_right_fits():
    # 4 episodes: two views right on >= 90 % of steps (both solved), two not (one solved)
    case = [[1, 1, 1, 0], [1.0, 0.95, 0.5, 0.1], 0.9]
    # everything right: no "other" side; nothing right: no "good" side, nothing needed
    full = [[1, 0], [1.0, 1.0], 0.9]
    none = [[1, 0], [0.0, 0.2], 0.9]
    a, b, c = _split(case, full, none)
    assert (a["p_good"], a["s_good"], a["s_bad"]) == (0.5, 1.0, 0.5)
    # 0.9 = 0.5 * 1.0 + 0.5 * need  ->  need = 0.8
    assert abs(a["need_bad"] - 0.8) < 1e-12
    assert (b["p_good"], b["s_good"], b["s_bad"], b["need_bad"]) == (1.0, 0.5, None, None)
    assert (c["p_good"], c["s_good"], c["s_bad"], c["need_bad"]) == (0.0, None, 0.5, None)


def test_bad_arguments_exit_with_one_line():
    r = subprocess.run([sys.executable, "bench/actor_views.py", "--run", "nope=/nowhere"],
                       cwd=ROOT, capture_output=True, text=True,
                       env={"PYTHONPATH": f"{ROOT}:{ROOT / 'bench'}", "PATH": "/usr/bin:/bin"})
    assert r.returncode != 0 and "TASK=DIR" in r.stderr.strip().splitlines()[-1]
