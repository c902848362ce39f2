"""Shared test settings.

JAX compiles dominate the suite's time: fixtures that build simulators and jitted functions are
module-scoped, and the persistent compilation cache (``twinrl._jaxconfig``) is on.
"""

import os

# Compile-bound suite: LLVM at -O0 and the legacy CPU fusion emitter compile about four times as
# fast together (see the Makefile's test target).
os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true "
                                   "--xla_backend_optimization_level=0 "
                                   "--xla_cpu_use_fusion_emitters=false "
                                   "--xla_cpu_parallel_codegen_split_count=1")

import jax  # noqa: E402
import pytest  # noqa: E402

import twinrl  # noqa: E402,F401  (compilation cache, quiet MJX import)


@pytest.fixture(scope="module")
def x64():
    """Float64 for the whole module (finite-difference checks are noise in float32)."""
    with jax.enable_x64(True):
        yield


# Longest files first (fresh clone, cold cache, 2 workers: each of these took 65-270 s). xdist's
# --dist loadfile hands files out in collection order, so the long ones start early and the short
# ones fill the gaps at the end instead of one worker finishing a long file alone.
# learn/test_sensing.py alone took 12 min (fresh clone, 2026-11-24): started last, one worker ran
# it while the other idled, and the suite took 27 min; its deployment half is its own file now.
_LONG_FIRST = ("learn/test_sensing.py", "learn/test_sensing_deploy.py", "test_loop_arm.py",
               "learn/test_imitation.py",
               "physics/test_foreign_arm.py", "physics/test_foreign_cylinder.py",
               "physics/test_foreign_contact.py", "physics/test_gradcheck.py",
               "learn/test_pods.py", "cli/test_train_cli.py",
               "physics/test_solver.py", "envs/test_envs.py", "envs/test_ppo.py",
               "real2sim/test_sysid.py", "cli/test_cli.py", "learn/test_hds.py",
               "sim2real/test_hybrid_residual.py", "learn/test_shac.py",
               "physics/test_foreign_drops.py")


def pytest_collection_modifyitems(items):
    rank = {p: i for i, p in enumerate(_LONG_FIRST)}
    # stable: the order within a file, and of the other files, is kept
    items.sort(key=lambda it: rank.get(it.nodeid.split("::")[0].removeprefix("tests/"),
                                       len(rank)))
