"""Shared test settings.

JAX compiles dominate the suite's time: fixtures that build simulators and jitted functions are
module-scoped, and the persistent compilation cache (``twinrl._jaxconfig``) is on.
"""

import os

# Compile-bound suite: LLVM at -O0 compiles about twice as fast (see the Makefile's test target).
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true "
                                   "--xla_backend_optimization_level=0")

import jax  # noqa: E402
import pytest  # noqa: E402

import twinrl  # noqa: E402,F401  (compilation cache, quiet MJX import)


@pytest.fixture(scope="module")
def x64():
    """Float64 for the whole module (finite-difference checks are noise in float32)."""
    with jax.enable_x64(True):
        yield
