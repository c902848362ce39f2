"""``bench/sensing.py --merge``: one result from several loop runs' ``sensing.json`` (one per twin),
with the pooled sign test the SAM-RL issue asks for and each twin's own figures."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _fake(path: Path, seed: int, outcomes: dict[str, list[int]], q_rank: float,
          **gate) -> Path:
    rows = [{"task": "needle_threading", "seed": seed, "mode": mode, "where": "real",
             "success": sum(ok) / len(ok), "return": 1.0, "real_steps": 10 * len(ok),
             "camera_steps": 2, "wall_s": 1.0, "q_rank_corr": q_rank, **gate,
             "episodes": {"seed": 1000 * seed, "success": [float(x) for x in ok]}}
            for mode, ok in outcomes.items()]
    path.write_text(json.dumps({"meta": {"command": f"run {seed}"}, "rows": rows,
                                "model_free": [], "sim_rows": []}))
    return path


def test_merge_pools_the_twins_and_keeps_each(tmp_path):
    # twin 0: selected solves 8 of 10, default 4 (selected alone on 5 starts, default alone on 1)
    a = _fake(tmp_path / "a.json", 0, {"selected": [1, 1, 1, 1, 1, 1, 1, 1, 0, 0],
                                       "default": [1, 1, 1, 0, 0, 0, 0, 0, 1, 0]}, 0.5)
    # twin 1: both solve the same 5 starts: no discordant pair
    b = _fake(tmp_path / "b.json", 1, {"selected": [1, 1, 1, 1, 1, 0, 0, 0, 0, 0],
                                       "default": [1, 1, 1, 1, 1, 0, 0, 0, 0, 0]}, 0.25)
    out = tmp_path / "merged"
    r = subprocess.run([sys.executable, "bench/sensing.py", "--merge", str(a), str(b), "--out",
                        str(out), "--camera-min-rank", "0.3"], cwd=ROOT, capture_output=True, text=True,
                       env={"PYTHONPATH": f"{ROOT}:{ROOT / 'bench'}", "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((out / "sensing.json").read_text())
    assert doc["meta"]["merged"] == ["run 0", "run 1"]
    pooled = doc["paired"][0]
    assert (pooled["episodes"], pooled["only_a"], pooled["only_b"]) == (20, 5, 1)
    assert pooled["difference"] == pytest.approx(4 / 20)
    assert pooled["sign_test_p"] == pytest.approx(0.21875)  # two-sided binomial, 5 of 6
    twin = {(x["seed"], x["mode"]): x for x in doc["per_twin"]}
    assert twin[(0, "selected")]["success"] == pytest.approx(0.8)
    lo, hi = twin[(0, "selected")]["ci95"]
    assert lo < 0.8 < hi and hi < 1.0  # Wilson: never the point estimate's degenerate interval
    assert twin[(0, "selected - default")]["difference"] == pytest.approx(0.4)
    assert twin[(1, "selected - default")]["sign_test_p"] == 1.0
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import pages
    finally:
        sys.path.remove(str(ROOT / "bench"))
    text = pages.sensing_table(doc)
    # the loop's camera: twin 0's Q (0.5) passes the gate (0.3), twin 1's (0.25) does not
    assert doc["camera_min_rank"] == 0.3
    loop = {r["seed"]: r for r in doc["rows"] if r["mode"] == "loop"}
    assert (loop[0]["deployed_from"], loop[1]["deployed_from"]) == ("selected", "default")
    assert loop[0]["episodes"]["success"] == [1.0] * 8 + [0.0] * 2
    assert twin[(0, "loop")]["success"] == pytest.approx(0.8)
    assert twin[(1, "loop")]["success"] == pytest.approx(0.5)
    assert "| needle_threading | 0 | 80 % (49-94) | 40 % (17-69) | – | 80 % (49-94): selected " \
           "(Q 0.50) | 10 | +40 (p 0.22) |" in text
    assert "| needle_threading | 1 | 50 % (24-76) | 50 % (24-76) | – | 50 % (24-76): default " \
           "(Q 0.25) | 10 | +0 (p 1) |" in text
    assert "| needle_threading | pooled | 65 % | 45 % | – | 65 % | 20 | +20 (p 0.22) |" in text


def test_the_loops_camera_is_what_its_check_in_the_identified_twin_chose(tmp_path):
    """A run whose ``camera_check`` stage kept the default camera deploys the default camera
    however well its Q ranks; the rank gate still comes first; a run that recorded no check
    falls back to the rank gate alone. The check is read from the run's own directory."""
    runs = {}
    for seed, camera in ((0, "default"), (1, "selected"), (2, None)):
        d = tmp_path / f"run{seed}"
        (d / "round1").mkdir(parents=True)
        (d / "summary.json").write_text(json.dumps(
            {"env": "needle_threading", "seed": seed,
             "final": {"round": 1, "q_rank_corr": 0.5 if seed != 1 else 0.1}}))
        if camera:
            (d / "round1" / "camera_check.json").write_text(json.dumps({"camera": camera}))
        runs[seed] = d
    files = []
    for seed, d in runs.items():
        p = _fake(tmp_path / f"s{seed}.json", seed, {"selected": [1, 1, 0, 0],
                                                     "default": [1, 1, 1, 0]}, 0.0)
        doc = json.loads(p.read_text())
        for r in doc["rows"]:
            del r["q_rank_corr"]  # as --run rows written before the gate was recorded
        doc["meta"]["settings"] = {"run": repr([f"needle_threading={d}"])}
        p.write_text(json.dumps(doc))
        files.append(str(p))
    out = tmp_path / "merged"
    r = subprocess.run([sys.executable, "bench/sensing.py", "--merge", *files, "--out", str(out),
                        "--camera-min-rank", "0.3"], cwd=ROOT, capture_output=True, text=True,
                       env={"PYTHONPATH": f"{ROOT}:{ROOT / 'bench'}", "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((out / "sensing.json").read_text())
    loop = {x["seed"]: x for x in doc["rows"] if x["mode"] == "loop"}
    # twin 0: Q passes the rank gate, the check kept the default; twin 1: the check chose Q's
    # camera but Q is below the gate; twin 2: no check recorded, the rank gate alone
    assert [loop[s]["deployed_from"] for s in (0, 1, 2)] == ["default", "default", "selected"]
    assert loop[0]["episodes"]["success"] == [1.0, 1.0, 1.0, 0.0]
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import pages
    finally:
        sys.path.remove(str(ROOT / "bench"))
    text = pages.sensing_table(doc)
    assert "75 % (30-95): default (Q 0.50, twin check)" in text
    assert "75 % (30-95): default (Q 0.10) |" in text
    assert "50 % (15-85): selected (Q 0.50) |" in text


def test_merge_names_a_bad_file(tmp_path):
    bad = tmp_path / "x.json"
    bad.write_text("not json")
    r = subprocess.run([sys.executable, "bench/sensing.py", "--merge", str(bad), "--out",
                        str(tmp_path)], cwd=ROOT, capture_output=True, text=True,
                       env={"PYTHONPATH": f"{ROOT}:{ROOT / 'bench'}", "PATH": "/usr/bin:/bin"})
    assert r.returncode != 0
    assert f"--merge {bad}: not a sensing.json" in r.stderr


def test_a_later_file_replaces_its_twins_rows_and_keeps_the_others(tmp_path):
    """``--merge OLD NEW``: NEW's twin replaces that twin's rows (and its loop row, derived anew)
    in OLD; OLD's other twins and their commands stay; each row names the command that
    measured it."""
    a = _fake(tmp_path / "a.json", 0, {"selected": [1, 1, 1, 1], "default": [1, 0, 0, 0]}, 0.5)
    b = _fake(tmp_path / "b.json", 1, {"selected": [1, 1, 0, 0], "default": [1, 0, 0, 0]}, 0.5)
    env = {"PYTHONPATH": f"{ROOT}:{ROOT / 'bench'}", "PATH": "/usr/bin:/bin"}

    def merge(files, out):
        r = subprocess.run([sys.executable, "bench/sensing.py", "--merge", *map(str, files),
                            "--out", str(out), "--camera-min-rank", "0.3"], cwd=ROOT,
                           capture_output=True, text=True, env=env)
        assert r.returncode == 0, r.stderr[-2000:]
        return json.loads((out / "sensing.json").read_text())

    doc = json.loads(b.read_text())
    doc["model_free"] = [{"task": "needle_threading", "algo": "sac", "twin_seed": 1,
                          "success": 0.1}]
    b.write_text(json.dumps(doc))
    first = merge([a, b], tmp_path / "m1")
    # twin 1 measured again: its Q now ranks below the gate, its default camera solves 3 of 4
    b2 = _fake(tmp_path / "b2.json", 1, {"selected": [0, 0, 0, 0], "default": [1, 1, 1, 0]},
               0.1)
    doc = json.loads(b2.read_text())
    doc["meta"]["command"] = "run 1 again"
    doc["model_free"] = [{"task": "needle_threading", "algo": "sac", "twin_seed": 1,
                          "success": 0.3}]
    b2.write_text(json.dumps(doc))
    second = merge([tmp_path / "m1" / "sensing.json", b2], tmp_path / "m2")
    assert second["meta"]["merged"] == ["run 0", "run 1 again"]
    rows = {(r["seed"], r["mode"]): r for r in second["rows"]}
    assert len(second["rows"]) == len(first["rows"]) == 6  # 2 twins x (selected, default, loop)
    assert rows[(0, "selected")] == {**{r["mode"]: r for r in first["rows"]
                                        if r["seed"] == 0}["selected"]}
    assert rows[(1, "selected")]["command"] == "run 1 again"
    assert rows[(1, "default")]["episodes"]["success"] == [1.0, 1.0, 1.0, 0.0]
    assert rows[(1, "loop")]["deployed_from"] == "default"
    assert rows[(1, "loop")]["success"] == pytest.approx(0.75)
    assert rows[(0, "loop")]["deployed_from"] == "selected"
    assert [r["success"] for r in second["model_free"]] == [0.3]  # replaced, not appended
    pooled = second["paired"][0]
    # twin 0: +3 starts for Q's choice; twin 1 now -3
    assert pooled["episodes"] == 8 and pooled["difference"] == pytest.approx(0.0)


def test_the_benchmarks_page_reproduces_a_merge_into_the_committed_file_from_scratch():
    """A twin re-measured and merged into the committed result (``--merge
    bench/results/sensing.json NEW/sensing.json``) is shown as the merge of every measuring
    command's directory, not of a file the reader does not have."""
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import pages
    finally:
        sys.path.remove(str(ROOT / "bench"))
    meta = {"merged": ["python bench/sensing.py --tasks peg_insertion --run "
                       "peg_insertion=/tmp/a/loop_0 --out /tmp/a/sens_0",
                       "python bench/sensing.py --tasks peg_insertion --run "
                       "peg_insertion=/tmp/b/loop_1 --out /tmp/b/sens_1"],
            "command": "python bench/sensing.py --merge bench/results/sensing.json "
                       "/tmp/b/sens_1/sensing.json --out bench/results"}
    assert pages.reproduce(meta, "") == [
        "python bench/sensing.py --tasks peg_insertion --run peg_insertion=RUN0 --out DIR0",
        "python bench/sensing.py --tasks peg_insertion --run peg_insertion=RUN1 --out DIR1",
        "python bench/sensing.py --merge DIR0/sensing.json DIR1/sensing.json --out bench/results"]
