"""Training on several processes with JAX's multi-controller runtime (``jax.distributed``).

Every process runs the same program on its own devices; ``jax.distributed.initialize`` joins
them, after which ``jax.devices()`` lists every process's devices and a jitted function over
arrays sharded on a mesh of all of them runs as one program, XLA inserting the collectives (the
all-reduce of a gradient taken as a mean over a sharded batch). twinrl's learners are written
that way (``twinrl.physics.parallel.batch_mesh``: one axis ``"batch"`` over ``jax.devices()``),
so the same code runs on one process or on many:

- ``initialize`` joins the runtime from explicit settings (``--coordinator HOST:PORT
  --num-processes N --process-id I``) or from the environment JAX reads itself (a SLURM job
  step with several tasks, an Open MPI launch, ``JAX_COORDINATOR_ADDRESS``); with neither it
  does nothing and the run is the one-process run it always was. On CPU the collectives between
  processes are Gloo's over TCP (``jax_cpu_collectives_implementation``), each process with its
  own CPU device(s).
- ``global_batch`` assembles a batch sharded over the global mesh from each process's rows;
  ``process_rows`` says which rows of a global batch are this process's. A batch drawn from one
  global key and then sliced is the same batch whatever the process count.
- ``to_host`` gathers a (sharded) pytree to NumPy on every process: a checkpoint of the whole
  state. ``is_writer``: process 0 alone writes files (checkpoints, logs, reports).
- ``classic_pmap``: JAX's original ``pmap`` for Brax PPO's multi-process path.
- Failure is loud: every process ends with one line on stderr and a non-zero status, never a
  hang. A peer that dies is seen at once by the next collective (its TCP connection is closed;
  ``guard`` turns that error into one line, exit status 1) or by the runtime (a missed heartbeat
  after ``heartbeat_s``, the coordinator's connection gone, peers not joined within
  ``timeout_s``: JAX aborts the process, exit status 134, and a filter cuts its C++ stack trace
  to one line, ``_one_line_fatal``).

``initialize`` must run before anything starts a JAX backend: importing this module starts none,
but importing the simulator (``twinrl.physics``, ``twinrl.envs``) does (it builds arrays), so a
program calls ``initialize`` first (``twinrl train`` does, before it imports the rest).
"""

from __future__ import annotations

import os
import subprocess
import sys
import traceback
import warnings
from contextlib import contextmanager
from typing import Any, Mapping

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["DistributedError", "requested", "initialize", "is_distributed", "is_writer",
           "process_rows", "global_batch", "to_host", "barrier", "global_mesh", "guard",
           "classic_pmap", "DEFAULT_TIMEOUT_S", "DEFAULT_HEARTBEAT_S"]

DEFAULT_TIMEOUT_S = 120
"""Seconds ``initialize`` waits for every process to join before it fails."""
DEFAULT_HEARTBEAT_S = 30
"""Seconds without a heartbeat after which the runtime declares a process dead."""


class DistributedError(RuntimeError):
    """The multi-process runtime could not start, a peer was lost, or what was asked cannot run
    on several processes: one line naming why."""


def requested(environ: Mapping[str, str] | None = None) -> bool:
    """Whether the environment asks for several processes: ``JAX_COORDINATOR_ADDRESS`` set, a
    SLURM job step with ``SLURM_NTASKS`` > 1, or an Open MPI launch of
    ``OMPI_COMM_WORLD_SIZE`` > 1 (the launchers whose settings JAX detects itself)."""
    env = os.environ if environ is None else environ

    def many(name):
        try:
            return int(env.get(name, "1")) > 1
        except ValueError:
            return False

    return (bool(env.get("JAX_COORDINATOR_ADDRESS"))
            or ("SLURM_JOB_ID" in env and "SLURM_STEP_NODELIST" in env and many("SLURM_NTASKS"))
            or ("OMPI_MCA_orte_hnp_uri" in env and many("OMPI_COMM_WORLD_SIZE")))


def _check_address(coordinator: str) -> None:
    host, sep, port = coordinator.rpartition(":")
    if not (sep and host and port.isdigit() and 0 < int(port) < 65536):
        raise DistributedError(f"coordinator {coordinator!r} is not HOST:PORT (e.g. "
                               f"10.0.0.1:1234)")


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, *, timeout_s: int = DEFAULT_TIMEOUT_S,
               heartbeat_s: int = DEFAULT_HEARTBEAT_S) -> int:
    """Join JAX's multi-process runtime; returns the process count (1: not distributed).

    Explicit settings take precedence; unset ones JAX fills in from a SLURM or Open MPI
    environment. With no setting and no such environment (``requested``) nothing is started.
    Must run before any JAX computation (the backends are created once). Raises
    ``DistributedError`` (one line) for inconsistent settings or when the processes have not all
    joined within ``timeout_s``."""
    explicit = (coordinator, num_processes, process_id)
    if all(x is None for x in explicit) and not requested():
        return 1
    if jax.distributed.is_initialized():
        return jax.process_count()
    if coordinator is not None:
        _check_address(coordinator)
    if num_processes is not None and num_processes < 1:
        raise DistributedError(f"num_processes must be >= 1, got {num_processes}")
    if process_id is not None and num_processes is not None and not 0 <= process_id < num_processes:
        raise DistributedError(f"process_id {process_id} is not in [0, {num_processes})")
    # Gloo is 0.9's default already; set it so a user's MPI-less CPU cluster never depends on it.
    if jax.config.jax_cpu_collectives_implementation is None:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    _one_line_fatal(process_id, num_processes)
    where = f"coordinator {coordinator or os.environ.get('JAX_COORDINATOR_ADDRESS', '(auto)')}"
    try:
        jax.distributed.initialize(coordinator, num_processes, process_id,
                                   initialization_timeout=int(timeout_s),
                                   heartbeat_timeout_seconds=int(heartbeat_s),
                                   shutdown_timeout_seconds=int(timeout_s))
    except Exception as e:  # JAX raises XlaRuntimeError/ValueError/RuntimeError with C++ detail
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise DistributedError(f"could not join the JAX distributed runtime ({where}, process "
                               f"{process_id} of {num_processes}) within {timeout_s} s: "
                               f"{first}") from None
    return jax.process_count()


_FILTER = r"""
import sys
head, out = sys.argv[1], sys.stdout.buffer
for line in sys.stdin.buffer:
    if b"Terminating process because the JAX distributed service" in line:
        status = line.partition(b"absl::Status: ")[2].strip().decode(errors="replace")
        out.write(f"{head} ({status or 'fatal error'})\n".encode())
        out.flush()
        break
    out.write(line)
    out.flush()
"""


def _one_line_fatal(process_id, num_processes) -> None:
    """Route this process's stderr through a small filter process that turns the runtime's fatal
    error into one line. When the coordination service loses a process (no heartbeat, a closed
    connection, peers that never registered) JAX 0.9's client aborts the process from C++: exit
    status 134 after ``F... Terminating process because the JAX distributed service detected
    fatal errors ...`` and a C++ stack trace. The runtime's client takes a callback for that,
    but jaxlib 0.9.2 cannot hand the status to Python (``std::bad_cast``, then
    ``std::terminate``), so the abort stays and its output is shortened instead: the filter
    passes every line through until that one, prints a single line naming the status, and drops
    the stack trace."""
    who = f"process {process_id if process_id is not None else '?'} of {num_processes or '?'}"
    head = (f"twinrl: error: {who}: the JAX distributed runtime stopped it (a process or the "
            f"coordinator died, or not every process joined in time)")
    try:
        sys.stderr.flush()
        proc = subprocess.Popen([sys.executable, "-I", "-S", "-c", _FILTER, head],
                                stdin=subprocess.PIPE, stdout=os.dup(2), close_fds=True)
    except OSError:
        return  # no filter: the runtime's own output stays
    os.dup2(proc.stdin.fileno(), 2)
    proc.stdin.close()


def is_distributed() -> bool:
    """Whether several processes take part (``jax.process_count() > 1``)."""
    return jax.process_count() > 1


def is_writer() -> bool:
    """Whether this process writes the run's files: process 0 (the only one when not
    distributed)."""
    return jax.process_index() == 0


def global_mesh() -> Mesh:
    """The one-axis ``("batch",)`` mesh over every process's devices."""
    # imported here: the simulator's modules start a JAX backend on import (``initialize`` first)
    from twinrl.physics.parallel import batch_mesh

    return batch_mesh(jax.devices())


def process_rows(rows: int, mesh: Mesh | None = None) -> slice:
    """The rows of a global batch of ``rows`` that this process holds on ``mesh`` (its devices'
    consecutive block). Raises ``ValueError`` if ``rows`` does not split over the devices."""
    mesh = mesh or global_mesh()
    n = mesh.devices.size
    if rows % n:
        raise ValueError(f"a global batch of {rows} rows cannot be split over {n} devices")
    per = rows // n
    mine = [i for i, d in enumerate(mesh.devices.flat) if d.process_index == jax.process_index()]
    if mine != list(range(mine[0], mine[0] + len(mine))):
        raise ValueError("this process's devices are not consecutive on the mesh")
    return slice(mine[0] * per, (mine[-1] + 1) * per)


def global_batch(local_tree, mesh: Mesh | None = None, rows: int | None = None):
    """Every leaf of ``local_tree`` (this process's rows, ``process_rows``) as one array whose
    leading axis is split over ``mesh`` (default ``global_mesh()``); ``rows``: the global leading
    size (default: the local one times the process count)."""
    mesh = mesh or global_mesh()

    def put(x):
        x = np.asarray(x)
        spec = PartitionSpec("batch", *([None] * (x.ndim - 1)))
        shape = None if rows is None else (int(rows),) + x.shape[1:]
        return jax.make_array_from_process_local_data(NamedSharding(mesh, spec), x, shape)

    return jax.tree_util.tree_map(put, local_tree)


def to_host(tree) -> Any:
    """``tree`` as NumPy on this process, the whole of every leaf: a leaf sharded over other
    processes' devices is gathered (a collective: every process must call it). One process:
    ``np.asarray`` of each leaf."""
    def gather(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            if x.is_fully_replicated:
                return np.asarray(x.addressable_data(0))
            from jax.experimental import multihost_utils
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(x)

    return jax.tree_util.tree_map(gather, tree)


def barrier(name: str) -> None:
    """Wait until every process reaches ``barrier(name)`` (nothing when not distributed)."""
    if is_distributed():
        from jax.experimental import multihost_utils
        multihost_utils.sync_global_devices(name)


@contextmanager
def guard(prefix: str = "twinrl"):
    """Around a distributed program: any error ends this process at once with a non-zero
    status, so its peers stop too (their next collective fails, or the runtime sees it gone)
    instead of waiting. ``os._exit``: JAX's exit handler would wait at the runtime's shutdown
    barrier for a peer that is not coming. What is printed: one line for a peer that was lost
    (a collective whose connection closed, the coordination service's error) or a
    ``DistributedError`` (exit status 1), and for twinrl's own errors, which name their cause
    in one line (exit status 2, the command line's status for bad input); the traceback for any
    other error (exit status 1). Not distributed: nothing, every error passes unchanged."""
    try:
        yield
    except DistributedError as e:
        print(f"{prefix}: error: {e}", file=sys.stderr, flush=True)
        os._exit(1)
    except Exception as e:
        if not is_distributed():
            raise
        who = f"process {jax.process_index()} of {jax.process_count()}"
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        if _runtime_failure(e):
            print(f"{prefix}: error: {who} lost its peers: {first}", file=sys.stderr, flush=True)
            os._exit(1)
        if type(e).__module__.startswith("twinrl"):
            print(f"{prefix}: error: {who}: {first}", file=sys.stderr, flush=True)
            os._exit(2)
        traceback.print_exc()
        print(f"{prefix}: error: {who} stopped: {type(e).__name__}: {first}", file=sys.stderr,
              flush=True)
        os._exit(1)


_LOST = ("gloo", "coordination service", "unavailable:", "deadline_exceeded",
         "connection reset", "connection closed", "connection refused", "heartbeat",
         "shutdown barrier")
"""Words of an error raised because another process is gone (Gloo's closed connection, the
coordination service's errors; JAX raises them as ``JaxRuntimeError`` or, from a collective
that was running, ``ValueError``); any other error is the program's own."""


def _runtime_failure(e: BaseException) -> bool:
    text = str(e).lower()
    return any(word in text for word in _LOST)


@contextmanager
def classic_pmap():
    """Under several processes, JAX's original ``pmap`` (``jax_pmap_shmap_merge=False``) for the
    duration: Brax 0.14.2's PPO needs it. Brax runs its epoch under ``jax.pmap`` over each
    process's devices, then takes ``jnp.mean`` of the epoch's metrics on the host; JAX 0.9's
    default ``pmap`` (built on ``shard_map``) returns arrays over every process's devices, and
    that ``jnp.mean`` copies them onto this process's devices alone, which JAX refuses
    (``INVALID_ARGUMENT: CopyArrays only supports destination device list of the same size as
    the array device lists``): PPO on two processes ended in its first epoch. The original
    ``pmap`` returns each process its own shards, as Brax expects. The setting is deprecated in
    JAX 0.9 (removed in 0.10, by when Brax must take the new ``pmap``'s arrays); its deprecation
    warning is silenced here. One process: nothing changes."""
    if not is_distributed():
        yield
        return
    before = jax.config.jax_pmap_shmap_merge

    def use(value):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            jax.config.update("jax_pmap_shmap_merge", value)

    use(False)
    try:
        yield
    finally:
        use(before)
