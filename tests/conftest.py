"""Shared test settings.

JAX compiles dominate the suite's time: fixtures that build simulators and jitted functions are
module-scoped, and the persistent compilation cache (``twinrl.jaxconfig``) is on.
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


# Longest files first, in the order of their time in a fresh-clone run (cold cache, 2 workers,
# 11d31f5, re-ranked where later commits cut a file: the files of >= 30 s, 182 s down to 32 s). xdist's --dist loadfile hands files out in
# collection order, so the long ones start early and the short ones fill the gaps at the end
# instead of one worker finishing a long file alone (learn/test_sensing.py, started last, once
# took 12 of a 27-minute suite while the other worker idled). Files move in this order as they
# get faster or slower: re-rank them from a run's junit XML (per file: the sum of its tests).
_LONG_FIRST = ("learn/test_sensing.py", "physics/test_foreign_cylinder.py",
               "cli/test_train_cli.py", "envs/test_envs.py", "learn/test_pods.py",
               "envs/test_arm.py", "cli/test_cli.py", "test_docs.py", "envs/test_ppo.py",
               "learn/test_imitation.py", "test_loop_arm_residual.py",
               "physics/test_foreign_drops.py", "physics/test_gradcheck.py",
               "physics/test_foreign_contact.py", "render/test_render.py",
               "physics/test_smooth.py", "physics/test_solver.py", "real2sim/test_sysid.py",
               "sim2real/test_hybrid_residual.py", "real2sim/test_visual.py",
               "envs/test_system.py", "learn/test_trajopt.py", "real/test_twin.py", "test_loop.py",
               "learn/test_sensing_deploy.py", "learn/test_hds.py", "learn/test_shac.py",
               "test_loop_arm.py", "physics/test_foreign_arm.py", "learn/test_runner.py",
               "cli/test_bad_input.py", "physics/test_contacts_mujoco.py", "physics/test_chain.py",
               "physics/test_polytopes.py", "physics/test_hfield.py")


def pytest_collection_modifyitems(items):
    rank = {p: i for i, p in enumerate(_LONG_FIRST)}
    # stable: the order within a file, and of the other files, is kept
    items.sort(key=lambda it: rank.get(it.nodeid.split("::")[0].removeprefix("tests/"),
                                       len(rank)))
