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
