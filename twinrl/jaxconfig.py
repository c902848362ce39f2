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
so child processes inherit it too. A script that imports JAX first (most do) has jaxlib read the
variable before twinrl can set it (``import jax`` sets it to 1 where unset), so then, unless the
user set the variable to another value or set ``jax_logging_level``, twinrl sets
``jax_logging_level`` to ``CRITICAL``, which lowers absl's level at run time (and JAX's Python
loggers' with it). ``set_verbose()`` (``twinrl --verbose``) shows warnings and errors again.

XLA's CPU fusion emitters (on by default in the pinned jaxlib) compile MJX's kinematics, a chain of
per-body transforms, into code whose run time grows exponentially with the kinematic tree's depth:
``smooth.kinematics`` of a 9-link chain of hinges with rotated frames takes 1,068 ms per call
with them and 0.59 ms without; inside an episode's scan, a physics step of the Panda tasks
15.6-16.6 ms against 0.07-0.15 ms (measured on 2 cores, ``bench/xla_cpu.py`` (in git history)).
``set_cpu_flags()`` therefore adds ``--xla_cpu_use_fusion_emitters=false`` to ``XLA_FLAGS`` on
import, unless the user's ``XLA_FLAGS`` already sets that flag or ``TWINRL_XLA_FLAGS=off``. XLA
reads the variable when JAX starts its first backend, so a process that ran JAX computations
before importing twinrl keeps its own setting and is told so once. The flag is added only under
the pinned jaxlib's series (0.9 and older): jaxlib 0.11.2's XLA no longer knows it and aborts
the whole process at its first computation on a flag it does not know ("Unknown flag in
XLA_FLAGS", seen on a GPU machine), and a version twinrl was not measured on gets XLA's defaults
rather than that risk.
"""

from __future__ import annotations

import contextlib
import functools
import io
import os
import sys
from pathlib import Path

_JAX_FIRST = "jax" in sys.modules
# ``import jax`` sets the variable to "1" where it was unset: after it, "1" is JAX's, not the user's
_QUIET = os.environ.get("TF_CPP_MIN_LOG_LEVEL") in ((None, "1") if _JAX_FIRST else (None,))
if _QUIET:
    os.environ["TF_CPP_MIN_LOG_LEVEL"] = "3"  # read by jaxlib on import, and by children

import jax  # noqa: E402

if _JAX_FIRST and _QUIET and jax.config.jax_logging_level in (None, "NOTSET"):
    # jaxlib read the variable when it was imported: set absl's level at run time instead
    jax.config.update("jax_logging_level", "CRITICAL")

CPU_FLAGS = "--xla_cpu_use_fusion_emitters=false"
"""What ``set_cpu_flags`` adds to ``XLA_FLAGS`` (module docstring)."""

CPU_FLAGS_BEFORE = (0, 10)
"""The jaxlib (major, minor) from which ``CPU_FLAGS`` is not added: 0.11.2's XLA rejects it,
0.10 was not tried."""


def xla_knows_cpu_flags(version: str | None = None) -> bool:
    """Whether the installed jaxlib's XLA (or ``version``'s) accepts ``CPU_FLAGS``."""
    if version is None:
        import jaxlib

        version = jaxlib.__version__
    try:
        major_minor = tuple(int(p) for p in version.split(".")[:2])
    except ValueError:
        return False
    return major_minor < CPU_FLAGS_BEFORE


def set_cpu_flags() -> bool:
    """Add ``CPU_FLAGS`` to ``XLA_FLAGS`` unless the user chose (module docstring); returns
    whether they are in effect for this process."""
    import warnings

    from jax._src import xla_bridge

    flags = os.environ.get("XLA_FLAGS", "")
    if "xla_cpu_use_fusion_emitters" in flags:
        return "xla_cpu_use_fusion_emitters=false" in flags
    if os.environ.get("TWINRL_XLA_FLAGS", "").strip().lower() in ("0", "off", "false", "no"):
        return False
    if not xla_knows_cpu_flags():
        return False
    if xla_bridge.backends_are_initialized():
        warnings.warn("twinrl: JAX started before twinrl was imported, so XLA's CPU fusion "
                      "emitters stay on and MJX runs the arm tasks ~100x slower on CPU; import "
                      f"twinrl first or set XLA_FLAGS={CPU_FLAGS}", stacklevel=3)
        return False
    os.environ["XLA_FLAGS"] = f"{flags} {CPU_FLAGS}".strip()
    _CPU_FLAGS_ADDED.append(True)
    return True


_CPU_FLAGS_ADDED: list[bool] = []  # set_cpu_flags added CPU_FLAGS to this process's XLA_FLAGS


def image_compiler_options() -> dict | None:
    """``compiler_options`` for a ``jax.jit`` that runs no MJX (images, point clouds and the fits
    made of them): XLA's CPU fusion emitters back on for that executable, where ``set_cpu_flags``
    turned them off for the process (None otherwise: off a CPU, or where the user chose).

    MJX's kinematics is what needs them off. A visual fit's Adam step (``fit_camera`` on push, 5
    frames at 64x64, three 96-point Sinkhorn solves a frame) runs 2.6x faster with them: 73-77
    ms against 196-199 ms on 2 cores, the Sinkhorn solves' logsumexp reductions most of the
    difference. And the JAX renderer's reverse pass on a 41-geom scene compiles right with them,
    where without them (at XLA's default optimisation level) one entry of its size gradient came
    out 104.0 against the 19.7 of central differences, forward mode and eager evaluation."""
    if not _CPU_FLAGS_ADDED or jax.default_backend() != "cpu":
        return None
    return {"xla_cpu_use_fusion_emitters": True}


def exact_matmuls(fn):
    """``fn`` with the matrix products it traces at float32's full precision
    (``jax.default_matmul_precision("highest")``), whatever the caller's default.

    On GPUs with TensorFloat-32 (NVIDIA Ampere and later) JAX's default lets a float32 product
    round its inputs to 10 bits of mantissa: a camera rotation applied to points a metre away
    then moves them by about a millimetre, and a Levenberg-Marquardt step's ``J.T @ J`` loses
    most of its digits. Measured on an H200 (jax 0.11.2, ``bench/render.py --visual --seeds
    0``): the camera fitted to 3.8 mm / 0.21 deg with JAX's default precision, 1.46 mm / 0.105
    deg with ``JAX_DEFAULT_MATMUL_PRECISION=highest`` for the whole process. The renderer, the
    point-cloud functions, the visual fits and ``ArmTask.fit_target_pose`` trace under this
    (their products are 3x3 rotations and small normal equations: nothing measurable to pay);
    on a CPU it changes nothing, since XLA's CPU code computes float32 products in float32
    whatever it is asked."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapped


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
