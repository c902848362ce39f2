"""``bench/dreamer_baseline.py``: without a Dreamer environment the bench keeps a ``dreamer`` row,
marked absent with the reason, and trains nothing."""

import importlib.util
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "bench"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("dreamer_baseline", BENCH / "dreamer_baseline.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_no_environment_gives_an_absent_row(bench, monkeypatch):
    monkeypatch.delenv("TWINRL_DREAMER_PYTHON", raising=False)
    exe, why = bench.dreamer_python()
    assert exe is None and "--dreamer-python" in why
    row = bench.train_dreamer("needle_threading", 100, 0.8, seed=3,
                              python="/nonexistent/dreamer-python")
    assert row["algo"] == "dreamer" and row["task"] == "needle_threading"
    assert row["twin_seed"] == 3 and "/nonexistent/dreamer-python" in row["absent"]
    assert "real_steps_trained" not in row
