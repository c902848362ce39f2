"""``twinrl.report``: tables and JSON outputs."""

import os

from twinrl import report


def test_tables_show_a_dash_for_missing_values(capsys):
    report.print_table("t", ["name", "return", "wall s"], [["a", None, 1.5], ["b", 2.0, None]])
    out = capsys.readouterr().out
    assert "None" not in out and out.count("—") == 2 and "1.5" in out


def test_write_json_fsyncs_the_file_before_the_rename_and_the_directory_after(tmp_path,
                                                                            monkeypatch):
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(a, b):
        events.append(("replace", str(b)))
        real_replace(a, b)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    path = report.write_json(tmp_path / "d" / "summary.json", {"x": 1})
    assert path.read_text() == '{\n  "x": 1\n}\n'
    assert events == [("fsync", str(path) + ".tmp"), ("replace", str(path)),
                      ("fsync", str(path.parent))]


# ------------------------------------------------------------------------------ the loop's report
# tests/data/loop_summary.json: the summary.json of a real `twinrl run` (cartpole_swingup, seed 0,
# one round, 2 shared cores), with each round's recorded real returns added.
import json  # noqa: E402
import re  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402

SUMMARY = Path(__file__).parent / "data" / "loop_summary.json"


def _summary():
    return json.loads(SUMMARY.read_text())


def _check_report(out: Path, md: str):
    cells = [c.strip() for line in md.splitlines() if line.startswith("|")
             for c in line.strip("|").split("|")]
    assert cells and not any(c in ("None", "nan", "NaN", "null", "") for c in cells), cells
    assert "None" not in md and "nan" not in md.lower().replace("nanmean", "")
    assert '{"' not in md, "a raw JSON dump"
    for link in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md):
        assert (out / link).stat().st_size > 5000, link
    return cells


def test_loop_report_reads_as_a_report(tmp_path):
    s = _summary()
    files = report.loop_report(tmp_path, s)
    md = (tmp_path / "report.md").read_text()
    cells = _check_report(tmp_path, md)
    assert set(files) == {"returns", "params", "report"}
    # the verdict: fraction of the oracle and the real steps, in words
    assert "99.0 % of the oracle" in md and "1000 real-twin steps" in md
    # what was identified, with its sd, and the (evaluation-only) error of each parameter
    assert "1.453 ± 1.157" in md and "mass/cart" in cells and "3.8 %" in cells
    assert "![returns" in md and "![params" in md and "[final.mp4](final.mp4)" in md


def test_loop_report_without_oracle_or_finished_round(tmp_path):
    s = _summary()
    for r in s["rounds"]:
        r["oracle_return"] = None
    s["final"].pop("fraction_of_oracle")
    report.loop_report(tmp_path / "a", s)
    md = (tmp_path / "a" / "report.md").read_text()
    _check_report(tmp_path / "a", md)
    assert "no oracle" in md
    s["rounds"] = s["rounds"][:1]
    s["final"] = dict(s["rounds"][0])
    s.pop("video")
    files = report.loop_report(tmp_path / "b", s)
    md = (tmp_path / "b" / "report.md").read_text()
    _check_report(tmp_path / "b", md)
    assert "nothing was deployed" in md and set(files) == {"report"}


def test_returns_plot_takes_the_model_free_curves(tmp_path):
    curve = [{"real_steps": n, "return": 10.0 * i} for i, n in enumerate(range(0, 5000, 500))]
    files = report.loop_report(tmp_path, _summary(), [{"algo": "sac", "seed": 0, "curve": curve}])
    md = (tmp_path / "report.md").read_text()
    assert "Model-free curves" in md and files["returns"].stat().st_size > 5000


@pytest.mark.parametrize("labels", [["real twin", "identified simulator"]])
def test_label_frames_burns_a_label_into_each_panel(labels):
    frames = [np.full((48, 128, 3), 200, np.uint8) for _ in range(3)]
    out = report.label_frames(frames, labels, band=14)
    assert len(out) == 3 and out[0].shape == frames[0].shape
    for half in (slice(0, 64), slice(64, 128)):
        band = out[0][:14, half]
        assert (band < 50).mean() > 0.5 and (band > 150).any()  # dark band, light text
    np.testing.assert_array_equal(out[2][14:], frames[2][14:])  # the picture below untouched
    assert not np.array_equal(out[0][:14, :64], out[0][:14, 64:])  # two different labels


def test_loop_report_sets_the_learner_beside_the_one_it_is_compared_with(tmp_path):
    s = _summary()
    s["rounds"][1]["compare"] = {"algo": "ppo", "sim_return": 190.0, "learn_s": 60.0,
                                 "deployed_algo": "shac", "deployed_learn_s": 30.0,
                                 "deployed_s_to_compare_final": 12.0}
    report.loop_report(tmp_path, s)
    md = (tmp_path / "report.md").read_text()
    cells = _check_report(tmp_path, md)
    assert "## Learning wall clock against a second learner" in md
    assert "`shac`" in cells and "`ppo`" in cells and "20.0 %" in cells
    s["rounds"][1]["compare"]["deployed_s_to_compare_final"] = None  # never reached it
    report.loop_report(tmp_path / "b", s)
    assert "never" in (tmp_path / "b" / "report.md").read_text()
    del s["rounds"][1]["compare"]
    report.loop_report(tmp_path / "c", s)
    assert "second learner" not in (tmp_path / "c" / "report.md").read_text()
