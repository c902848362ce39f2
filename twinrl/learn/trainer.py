"""One resumable epoch loop for every trainer (PODS, HDS, SHAC): restore, place, run, record.

The contract of ``twinrl.learn.common`` (Brax's ``train``, made resumable) has the same outer
shape in every algorithm: build the initial state, hand it to ``restore`` as the template to
fill, check the restored epoch against the restored metrics, then per epoch run the algorithm's
update, record its metrics (``MetricLog``: cumulative wall clock), call ``progress_fn`` and
``checkpoint_fn``. That shape lives here once, so a trainer states only its epoch::

    state, log, done = resume(restore, state, MyState)
    state = run_epochs(state, log, done, config.epochs, epoch, progress_fn=progress_fn,
                       checkpoint_fn=checkpoint_fn)

where ``epoch(e, state) -> (state, row)`` returns the next state and the epoch's metrics after
``epoch`` (``env_steps``, ``return``, ...). Placement on devices is the trainer's choice
(``replicate`` for what every device holds; ``twinrl.physics.parallel.shard_batch`` for batches).
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from twinrl.learn import distributed
from twinrl.learn.common import CheckpointFn, MetricLog, ProgressFn, RestoreFn
from twinrl.physics.parallel import shard_batch

__all__ = ["replicate", "check_batch", "restore_state", "check_restored", "resume",
           "run_epochs", "jit_sharded_epoch", "EpochFn"]

EpochFn = Callable[[int, Any], tuple[Any, dict[str, Any]]]
"""``(epoch index e (0-based), state) -> (state after the epoch, metrics of the epoch)``."""


def replicate(tree, mesh):
    """Place ``tree`` on every device of ``mesh`` (the same placement every epoch, so the jitted
    epoch functions compile once: a fresh init and a jit output would otherwise differ)."""
    return jax.device_put(_from_host(tree), NamedSharding(mesh, PartitionSpec()))


def _from_host(tree):
    """Under ``jax.distributed``, ``tree`` as host (NumPy) arrays: an array committed to this
    process's device (MJX's ``make_data`` commits its arrays) cannot be placed on a global mesh
    ("does not support cross-host device transfers"), a host array can (every process holds the
    same value and places its own shards). One process: ``tree`` unchanged."""
    return distributed.to_host(tree) if distributed.is_distributed() else tree


def jit_sharded_epoch(step: Callable, state, mesh, batched: tuple[str, ...], n_out: int):
    """``(state placed, jitted step)`` for a NamedTuple ``state`` whose ``batched`` fields have the
    environments on their leading axis: those fields are split over the devices of ``mesh``, the
    rest replicated, and ``step(state) -> (state, *n_out - 1 replicated outputs)`` keeps that
    layout (explicit shardings: an output laid out differently from its input would recompile the
    step on its second call)."""
    state = _from_host(state)
    state = replicate(state, mesh)._replace(
        **{k: shard_batch(getattr(state, k), mesh) for k in batched})
    layout = jax.tree_util.tree_map(lambda x: x.sharding, state)
    replicated = NamedSharding(mesh, PartitionSpec())
    return state, jax.jit(step, in_shardings=(layout,),
                          out_shardings=(layout,) + (replicated,) * (n_out - 1))


def check_batch(batch_size: int, what: str = "batch_size") -> int:
    """The device count, after checking that ``batch_size`` splits evenly over it."""
    n = len(jax.devices())
    if batch_size % n:
        raise ValueError(f"{what} ({batch_size}) must be a multiple of the device count ({n}) "
                         f"to shard the rollouts over jax.devices()")
    return n


def restore_state(restore: RestoreFn | None, state, cls):
    """Apply the contract's ``restore`` to the template ``state``; returns ``(state, history)``.

    A restored dict becomes ``cls``; every leaf takes its template's kind (NumPy stays NumPy with
    the template's dtype, e.g. int64 step counters; the rest become JAX arrays)."""
    if restore is None:
        return state, None
    restored, history = restore(state)
    if isinstance(restored, dict):
        restored = cls(**restored)
    restored = jax.tree_util.tree_map(lambda x, t: np.asarray(x, np.asarray(t).dtype)
                                      if isinstance(t, np.ndarray) else jnp.asarray(x),
                                      restored, state)
    return restored, history


def check_restored(state, log: MetricLog) -> int:
    """Completed epochs, after checking that the state's ``epoch`` agrees with its metrics."""
    done = len(log.history.get("epoch", []))
    if int(state.epoch) != done:
        raise ValueError(f"restored state is at epoch {int(state.epoch)} but its metrics record "
                         f"{done} epochs")
    return done


def resume(restore: RestoreFn | None, state, cls) -> tuple[Any, MetricLog, int]:
    """``(state, log, done)``: the restored (or initial) state, its metric log and the number of
    completed epochs the loop continues from."""
    state, history = restore_state(restore, state, cls)
    log = MetricLog(history)
    return state, log, check_restored(state, log)


def run_epochs(state, log: MetricLog, done: int, epochs: int, epoch: EpochFn, *,
               progress_fn: ProgressFn | None = None,
               checkpoint_fn: CheckpointFn | None = None):
    """Epochs ``done .. epochs - 1`` of ``epoch``; after each, its metrics are recorded (with
    ``epoch = e + 1`` first and ``wall_s`` last), then ``progress_fn(e + 1, row)`` and
    ``checkpoint_fn(e + 1, state, metrics so far)`` are called. Returns the final state."""
    for e in range(done, int(epochs)):
        state, metrics = epoch(e, state)
        row = log.record(epoch=e + 1, **metrics)
        if progress_fn is not None:
            progress_fn(e + 1, row)
        if checkpoint_fn is not None:
            checkpoint_fn(e + 1, state, log.as_dict())
    return state
