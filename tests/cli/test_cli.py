"""End-to-end tests of the ``twinrl`` command, one slow test per command, as a user runs it."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from twinrl.real.dataset import read

ROOT = Path(__file__).resolve().parents[2]


def twinrl(*args, timeout=900):
    # every progress line, however quick the stage (a warm compilation cache makes them quick)
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "TWINRL_PROGRESS_AFTER": "0"}
    return subprocess.run([sys.executable, "-m", "twinrl.cli", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT, env=env)


@pytest.mark.slow
def test_gradcheck_command_on_a_user_mjcf_path(tmp_path):
    # A user's own MJCF by path, with contacts: a free box thrown along a plane (keyframe start),
    # named like a bundled scene to check it does not get that scene's scenario.
    src = (ROOT / "tests/physics/foreign/box_sliding.xml").read_text()
    (tmp_path / "push.xml").write_text(src)
    out = twinrl("gradcheck", str(tmp_path / "push.xml"), "--x64", "--horizon", "20",
                 "--scenario", "zero", "--strict", "--out", str(tmp_path / "gc"))
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    summary = json.loads((tmp_path / "gc/summary.json").read_text())
    assert summary["scene"] == "push" and summary["scenario"] == "zero"
    assert summary["nan_count"] == 0 and summary["constrained_steps"] >= 10
    assert summary["max_rel_error"] <= 1e-4 and summary["passed_strict"] is True
    assert summary["unjudged"] == []
    groups = {g["group"]: g for g in summary["groups"]}
    assert groups["params.friction"]["resolved"] >= 1 and groups["qpos"]["entries"] == 6
    assert {"group", "index", "grad", "fd", "rel_err", "status"} <= set(summary["rows"][0])
    assert "PASS" in out.stdout and "max rel err" in out.stdout
    assert "Failed to import warp" not in out.stdout
    # a check of more than a few seconds says what it is doing: tracing, compiling, differencing
    assert "push [" in out.stdout and "tracing the gradient of a 20-step rollout" in out.stdout
    assert "differencing" in out.stdout and "rollouts in batches of" in out.stdout
    # --rtol 0 is a usage error (it used to mean the default tolerance)
    bad = twinrl("gradcheck", str(tmp_path / "push.xml"), "--rtol", "0")
    assert bad.returncode == 2 and "--rtol must be > 0" in bad.stderr


def test_xla_cache_warnings_are_quiet_unless_asked_for():
    # every executable loaded from the compilation cache makes XLA's C++ runtime log a warning
    # (and, on some CPUs, two cpu_aot_loader errors); twinrl sets TF_CPP_MIN_LOG_LEVEL=3 before
    # JAX is imported, unless the user set it
    code = "import os, twinrl; print(os.environ['TF_CPP_MIN_LOG_LEVEL'])"
    for given, seen in ((None, "3"), ("0", "0")):
        env = {k: v for k, v in os.environ.items() if k != "TF_CPP_MIN_LOG_LEVEL"}
        if given is not None:
            env["TF_CPP_MIN_LOG_LEVEL"] = given
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             env=env, cwd=ROOT, timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.strip() == seen and out.stderr == ""  # nor "Failed to import warp"


ABSL_LINE = re.compile(r"^[IWE]\d{4} \d\d:\d\d:\d\d", re.M)  # e.g. "E1123 10:25:44.2"


def _cache_runs(tmp_path, script, runs):
    """``script`` run once per ``(args, extra environment)`` of ``runs``, in order, with a
    fresh compilation cache and no log level of the caller's; their stderr."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("TF_CPP_MIN_LOG_LEVEL", "JAX_COMPILATION_CACHE_DIR")}
    env["TWINRL_CACHE_DIR"] = str(tmp_path / "cache")
    logs = []
    for args, extra in runs:
        out = subprocess.run([sys.executable, "-c", script, *args], capture_output=True,
                             text=True, env={**env, **extra}, cwd=ROOT, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        logs.append(out.stderr)
    return logs


def test_the_runtime_log_is_hidden_by_default_and_shown_with_verbose(tmp_path):
    # a jitted function loaded back from a fresh compilation cache, after `twinrl [--verbose] envs`
    script = ("import sys\n"
              "from twinrl import cli\n"
              "import jax, jax.numpy as jnp\n"
              "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0)\n"
              "assert cli.main(sys.argv[1:]) == 0\n"
              "print(jax.jit(lambda x: jnp.sin(x) * 3 + 1)(jnp.ones(3)))\n")
    envs = ["envs", "--out", str(tmp_path / "envs")]
    logs = _cache_runs(tmp_path, script, [(envs, {}), (envs, {}), (["--verbose", *envs], {})])
    assert not ABSL_LINE.search(logs[1]) and "cpu_aot_loader" not in logs[1], logs[1][-2000:]
    assert ABSL_LINE.search(logs[2]), logs[2][-2000:]  # the cache hit's warning at least


def test_a_script_that_imports_jax_first_is_quiet_too(tmp_path):
    # most scripts `import jax` before twinrl: jaxlib has read TF_CPP_MIN_LOG_LEVEL by then
    # (import jax sets it to 1), so twinrl lowers absl's level at run time; a level the user
    # set is theirs
    script = ("import jax, jax.numpy as jnp\n"
              "import twinrl\n"
              "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0)\n"
              "print(jax.jit(lambda x: jnp.cos(x) * 2 - 1)(jnp.ones(3)))\n")
    # compile, load from the cache, load with the user's level
    logs = _cache_runs(tmp_path, script, [([], {}), ([], {}), ([], {"TF_CPP_MIN_LOG_LEVEL": "0"})])
    assert not ABSL_LINE.search(logs[1]), logs[1][-2000:]
    assert ABSL_LINE.search(logs[2]), logs[2][-2000:]


def test_malformed_mjcf_gets_one_clear_line(tmp_path):
    bad = tmp_path / "broken.xml"
    bad.write_text("<mujoco><worldbody><body><geom type='sphere'/></body></worldbody>")
    out = twinrl("gradcheck", str(bad))
    assert out.returncode == 2 and "malformed MJCF" in out.stderr and str(bad) in out.stderr
    assert "Traceback" not in out.stderr


@pytest.mark.slow
def test_envs_collect_and_render(tmp_path):
    out = twinrl("envs", "--out", str(tmp_path / "envs"))
    assert out.returncode == 0, out.stderr[-2000:]
    tasks = {t["name"]: t for t in json.loads((tmp_path / "envs/summary.json").read_text())["tasks"]}
    assert {"pendulum_swingup", "cartpole_balance", "cartpole_swingup", "push"} <= set(tasks)
    assert tasks["push"]["contacts"] and not tasks["cartpole_swingup"]["contacts"]
    assert tasks["push"]["action_dim"] == 2

    out = twinrl("collect", "--env", "pendulum_swingup", "--episodes", "2", "--images",
                 "--size", "32", "24", "--out", str(tmp_path / "c"))
    assert out.returncode == 0, out.stderr[-2000:]
    summary = json.loads((tmp_path / "c/summary.json").read_text())
    ds = read(tmp_path / "c/dataset")
    assert len(ds) == summary["steps"] and ds.num_episodes == 2
    assert ds.images["rgb"].shape[1:] == (24, 32, 3)
    # the default policy excites: levels held for 3-15 steps, so the system travels
    a = np.asarray(ds.action)
    assert summary["policy"] == "excite" and np.all(np.abs(a) <= 1)
    held = np.mean(np.all(a[1:] == a[:-1], axis=-1))
    assert 0.6 < held < 0.95, held

    out = twinrl("render", "--env", "cartpole_swingup", "--real", "--steps", "10",
                 "--size", "64", "48", "--out", str(tmp_path / "r"))
    assert out.returncode == 0, out.stderr[-2000:]
    files = json.loads((tmp_path / "r/summary.json").read_text())["files"]
    for kind in ("rgb", "depth", "segmentation", "video"):
        assert Path(files[kind]).stat().st_size > 0
