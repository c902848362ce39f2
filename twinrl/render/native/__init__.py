"""The renderer's images and their gradients in C++: XLA FFI custom calls on the CPU.

``Renderer.render`` draws its images with ``render.cc``: the same arithmetic as the JAX
renderer, a packet of pixels at a time (a 4-column tile, one pixel a SIMD lane: 16 float32 or 8
float64 lanes where the CPU has AVX-512), the frames' tile rows split across the cores, where XLA
runs the JAX version as hundreds of passes over (pixel, surface) arrays. A geom no ray of a
16x16 block passes near is left out there, and a surface no lane of a packet needs is neither
searched, shaded nor differentiated. Reverse-mode derivatives (``jax.grad``, ``jax.vjp``,
``jax.jacrev``) run its reverse pass: each packet drawn again and differentiated backwards, by
hand through compositing and shading and on forward-mode numbers through each surface's
geometry, into the camera's and the geoms' cotangents. Forward mode (``jax.jvp``,
``jax.jacfwd``) and second derivatives go through the JAX version (the render's custom JVP,
``twinrl.render.linear``). Scenes with meshes stay in JAX.

The library is compiled on first use with the system's C++ compiler (``$CXX``, else ``g++``,
``c++`` or ``clang++``; about 20 s, once) into the compilation cache directory
(``$TWINRL_CACHE_DIR/native``; a temporary directory when the cache is off), keyed by the
source, the compiler, jaxlib and the CPU. Without a compiler, or with
``TWINRL_NATIVE_RENDER=0``, every image is drawn in JAX as before; ``status()`` says which and
why. ``TWINRL_RENDER_THREADS`` caps the threads (default: the cores this process may use).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

import jax

__all__ = ["available", "disabled", "status", "library", "SOURCE", "TARGETS", "VJP_TARGETS"]

SOURCE = Path(__file__).with_name("render.cc")
TARGETS = {"float32": "twinrl_render_f32", "float64": "twinrl_render_f64"}
VJP_TARGETS = {"twinrl_render_f32": "twinrl_render_vjp_f32",
               "twinrl_render_f64": "twinrl_render_vjp_f64"}
FLAGS = ["-O3", "-march=native", "-std=c++17", "-shared", "-fPIC", "-fno-math-errno", "-Wno-psabi",
         "-pthread"]


def _compiler() -> str | None:
    cxx = os.environ.get("CXX")
    if cxx:
        return shutil.which(cxx) or cxx
    for name in ("g++", "c++", "clang++"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _cpu_key() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((ln for ln in f if ln.startswith(("flags", "Features"))), "")
    except OSError:
        flags = ""
    return platform.machine() + flags


def _directory() -> Path:
    from twinrl.jaxconfig import cache_dir

    base = cache_dir()
    if base is not None:
        try:
            (base / "native").mkdir(parents=True, exist_ok=True)
            return base / "native"
        except OSError:
            pass
    return Path(tempfile.mkdtemp(prefix="twinrl-native-"))


def _build(cxx: str) -> Path:
    import jaxlib

    include = jax.ffi.include_dir()
    key = hashlib.sha256()
    for part in (SOURCE.read_bytes(), cxx.encode(), jaxlib.__version__.encode(),
                 " ".join(FLAGS).encode(), _cpu_key().encode()):
        key.update(part)
    out = _directory() / f"render-{key.hexdigest()[:16]}.so"
    if out.exists():
        return out
    tmp = out.with_name(f"{out.stem}.{os.getpid()}.tmp.so")
    proc = subprocess.run([cxx, *FLAGS, f"-I{include}", str(SOURCE), "-o", str(tmp)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        tmp.unlink(missing_ok=True)
        first = next((ln for ln in proc.stderr.splitlines() if "error" in ln),
                     proc.stderr.strip()[:200])
        raise RuntimeError(f"{Path(cxx).name} failed on {SOURCE.name}: {first}")
    os.replace(tmp, out)  # atomic: parallel test workers may build at once
    return out


def probe() -> tuple[Path | None, str]:
    """Build (or find in the cache) and register the kernel now, ignoring any earlier answer:
    ``(library path or None, one line saying whether it is on and if not, why)``. Reads
    ``TWINRL_NATIVE_RENDER`` and ``CXX`` at the call; ``available()`` and friends ask once."""
    flag = os.environ.get("TWINRL_NATIVE_RENDER", "").strip().lower()
    if flag in ("0", "off", "false", "no"):
        return None, "off (TWINRL_NATIVE_RENDER)"
    if jax.default_backend() != "cpu":
        return None, f"not used on {jax.default_backend()} (a CPU kernel)"
    cxx = _compiler()
    if cxx is None:
        return None, "no C++ compiler found (set CXX, or install g++)"
    try:
        path = _build(cxx)
        lib = ctypes.CDLL(str(path))
        for dtype, name in TARGETS.items():
            suffix = "F32" if dtype == "float32" else "F64"
            for target, sym in ((name, "TwinrlRender" + suffix),
                                (VJP_TARGETS[name], "TwinrlRenderVjp" + suffix)):
                jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(lib, sym)),
                                            platform="cpu")
    except (OSError, RuntimeError, AttributeError) as e:
        return None, f"not built: {e}"
    return path, f"on ({path})"


_load = functools.cache(probe)


_OFF: list[bool] = []


@contextlib.contextmanager
def disabled():
    """Draw every image in JAX inside this block (renders traced inside it; to compare the two,
    or to time the JAX version)."""
    _OFF.append(True)
    try:
        yield
    finally:
        _OFF.pop()


def available() -> bool:
    """Whether images (and their reverse-mode gradients) are drawn by the C++ kernel (built
    on first call)."""
    return not _OFF and _load()[0] is not None


def status() -> str:
    """One line: whether the kernel is on, and if not, why."""
    return _load()[1]


def library() -> Path | None:
    """The compiled kernel's path (None where it is not available)."""
    return _load()[0]
