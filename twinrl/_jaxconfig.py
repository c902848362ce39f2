"""Settings twinrl applies on import: the persistent compilation cache, a quiet MJX import.

Compiling a gradient through contacts takes tens of seconds; the cache makes the second run of any
command (and the test suite) skip it. It lives in ``$TWINRL_CACHE_DIR`` if set, else
``$XDG_CACHE_HOME/twinrl/jax`` (``~/.cache/twinrl/jax``). ``TWINRL_CACHE_DIR=off`` disables it.
A cache directory the user already configured for JAX (``JAX_COMPILATION_CACHE_DIR``) is left alone.

XLA's C++ runtime logs, for every executable it loads from that cache, a warning ("W... Assume
version compatibility. PjRt-IFRT does not track XLA executable versions") and, on CPUs without
some tuning features, two errors ("E... cpu_aot_loader.cc:220] Loading XLA:CPU AOT result. Target
machine feature +prefer-no-scatter is not supported ... SIGILL") that are harmless here (the
entries were compiled on this machine): dozens of lines per command. Unless
``TF_CPP_MIN_LOG_LEVEL`` is set, it is set to 3 (fatal only) here, before JAX is first imported,
so child processes inherit it too; a process that imported JAX before twinrl keeps its own
setting. ``set_verbose()`` (``twinrl --verbose``) shows warnings and errors again.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
from pathlib import Path

if "jax" not in sys.modules:
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

import jax  # noqa: E402


def set_verbose() -> None:
    """Show the XLA/absl runtime's warnings and errors (and JAX's Python warnings), from now on
    and in child processes started later."""
    os.environ["TF_CPP_MIN_LOG_LEVEL"] = "1"
    jax.config.update("jax_logging_level", "WARNING")  # sets absl's minimum level at run time


def import_mjx_quietly() -> None:
    """Import ``mujoco.mjx`` without its unconditional "Failed to import warp" prints.

    mujoco-mjx 3.17 prints two lines to stdout on import when the optional Warp backend is absent
    (CPU installs always). They would pollute every command's output and any JSON printed on stdout.
    Other output of the import is passed through.
    """
    if "mujoco.mjx" in sys.modules:
        return
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        import mujoco.mjx  # noqa: F401
    rest = [ln for ln in buf.getvalue().splitlines()
            if ln.strip() and not ln.startswith(("Failed to import warp", "Failed to import mujoco_warp"))]
    if rest:
        print("\n".join(rest))


def cache_dir() -> Path | None:
    env = os.environ.get("TWINRL_CACHE_DIR")
    if env is not None:
        return None if env.strip().lower() in ("", "0", "off", "none", "false") else Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "twinrl" / "jax"


def enable_compilation_cache() -> Path | None:
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return Path(os.environ["JAX_COMPILATION_CACHE_DIR"])
    path = cache_dir()
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None  # read-only home: run without a cache rather than fail
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
