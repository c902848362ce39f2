"""What every benchmark's result file records, and how it is written.

Each bench in ``bench/`` writes one JSON file under ``--out DIR`` (default ``bench/results``)::

    {"meta": {...}, ...the bench's own results...}

``meta`` (``metadata``) says how to reproduce the figures and where they were measured: the
``command`` line, the git ``commit`` (with ``dirty`` when the work tree had changes), the
``machine`` (cores, CPU model, platform, JAX's device), the UTC ``date``, the package
``versions`` and the bench's ``settings`` (its parsed arguments). ``bench/pages.py`` renders
these files into ``docs/benchmarks.md`` and the README's results table.
"""

from __future__ import annotations

import datetime as _dt
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench" / "results"


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo`` (Linux), else ``platform.processor()``."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def git_commit() -> tuple[str, bool]:
    """The checkout's commit and whether its tracked files differ from it ("unknown" outside git)."""
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True,
                                text=True, check=True).stdout.strip()
        dirty = bool(subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                                    cwd=ROOT, capture_output=True, text=True).stdout.strip())
        return commit, dirty
    except (OSError, subprocess.CalledProcessError):
        return "unknown", False


def versions() -> dict[str, str]:
    """Versions of the packages a figure depends on (those importable here)."""
    out = {"python": sys.version.split()[0]}
    for name in ("twinrl", "jax", "jaxlib", "mujoco", "mujoco_mjx", "brax", "numpy"):
        try:
            from importlib.metadata import version

            out[name] = version(name.replace("_", "-"))
        except Exception:  # not installed
            continue
    return out


def machine() -> dict[str, Any]:
    """Where a figure was measured: cores, CPU model, platform, the load average when the result
    was written, and JAX's first device."""
    info: dict[str, Any] = {"cores": os.cpu_count(), "cpu_model": cpu_model(),
                            "platform": platform.platform()}
    if hasattr(os, "getloadavg"):  # other work on the machine slows every timing down
        info["load_average"] = [round(x, 2) for x in os.getloadavg()]
    try:
        import jax

        info["device"] = str(jax.devices()[0])
    except Exception:
        info["device"] = "unknown"
    return info


def metadata(args=None, argv: list[str] | None = None) -> dict[str, Any]:
    """The ``meta`` block of a result file: command, commit, machine, date, versions and the
    bench's settings (``args``, an ``argparse.Namespace``, as strings)."""
    argv = sys.argv if argv is None else argv
    script = Path(argv[0]).resolve()
    try:
        script_name = str(script.relative_to(ROOT))
    except ValueError:
        script_name = str(argv[0])
    commit, dirty = git_commit()
    meta = {"command": " ".join(["python", script_name, *argv[1:]]), "commit": commit,
            "dirty": dirty, "machine": machine(),
            "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "versions": versions()}
    if args is not None:
        meta["settings"] = {k: str(v) for k, v in vars(args).items()}
    return meta


def write_result(path: str | os.PathLike, data: dict[str, Any], args=None) -> Path:
    """Write ``{"meta": metadata(args), **data}`` to ``path`` (atomic, durable; see
    ``twinrl.report.write_json``); a ``meta`` already in ``data`` is kept and completed."""
    from twinrl.report import write_json

    meta = {**data.get("meta", {}), **metadata(args)}  # the common keys describe this run
    return write_json(path, {"meta": meta, **{k: v for k, v in data.items() if k != "meta"}})
