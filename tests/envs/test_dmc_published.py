"""``bench/dmc.py``'s published Control Suite figures: one entry per registered ``dmc/`` task,
each a number with its source and budget or None with the reason, and ``--published-only``
rewrites that block of a result without touching its runs or their ``meta``."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from twinrl import envs

BENCH = Path(__file__).resolve().parents[2] / "bench"


@pytest.fixture(scope="module")
def dmc():
    sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location("bench_dmc", BENCH / "dmc.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_every_registered_task_has_published_figures_with_sources(dmc):
    assert set(dmc.PUBLISHED) == set(envs.names("dmc"))
    for task, figs in dmc.PUBLISHED.items():
        assert figs, task
        for f in figs:
            assert f["source"].startswith("https://"), (task, f)
            if f["return"] is None:
                assert f["reason"], (task, f)
                continue
            assert 0 <= f["return"] <= 1000 and f["obs"] == "states", (task, f)
            # the reported figure is the curve's point at the reported budget, in control steps
            assert f["curve"][str(f["steps"])][0] == f["return"], (task, f)
            assert f["steps"] == 2 * f["agent_steps"], (task, f)


def test_nearest_published_point_matches_the_control_steps(dmc):
    near = dmc.nearest_published("dmc/cartpole-swingup", 204_800)
    assert {v[0] for v in near.values()} == {200_000}
    assert dmc.nearest_published("dmc/cartpole-swingup", None) == {}


def test_published_only_keeps_runs_and_meta(dmc, tmp_path, monkeypatch):
    path = tmp_path / "dmc.json"
    runs = [{"task": "dmc/cartpole-swingup", "algo": "ppo", "seed": 0, "return": 1.5}]
    meta = {"command": "python bench/dmc.py --budget 7", "commit": "b" * 40}
    path.write_text(json.dumps({"meta": meta, "runs": runs, "published": {}}))
    monkeypatch.setattr(sys, "argv", ["bench/dmc.py", "--published-only", "--out", str(tmp_path)])
    assert dmc.main(["--published-only", "--out", str(tmp_path)]) == 0
    doc = json.loads(path.read_text())
    assert doc["runs"] == runs
    assert {k: doc["meta"][k] for k in meta} == meta
    assert doc["meta"]["published_written"]["command"].endswith(f"--out {tmp_path}")
    assert set(doc["published"]) == set(dmc.PUBLISHED)
    with pytest.raises(SystemExit, match="does not exist"):
        dmc.main(["--published-only", "--out", str(tmp_path / "none")])
