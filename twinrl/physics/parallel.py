"""Shard batches of rollouts over ``jax.devices()``.

A batch (leading axis) of states/actions is laid out over a one-axis device mesh named
``"batch"`` with ``jax.sharding.NamedSharding``; a jitted ``vmap`` then runs each device's slice
on that device, and XLA inserts no communication because rollouts are independent. One device is
the degenerate case (the result is the same array). Multi-host runs initialise
``jax.distributed`` first; ``jax.devices()`` then spans hosts and the same code applies.
"""

from __future__ import annotations

from typing import Sequence

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["batch_mesh", "shard_batch"]


def batch_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A one-axis mesh ``("batch",)`` over ``devices`` (default: all of ``jax.devices()``)."""
    return Mesh(np.asarray(devices if devices is not None else jax.devices()), ("batch",))


def shard_batch(tree, mesh: Mesh | None = None):
    """Place every leaf of ``tree`` with its leading axis split over the mesh's devices.

    Raises ``ValueError`` if a leaf's leading axis is not divisible by the device count.
    """
    mesh = mesh or batch_mesh()
    n = mesh.devices.size

    def put(x):
        x = jax.numpy.asarray(x)
        if x.ndim == 0 or x.shape[0] % n:
            raise ValueError(f"batch axis of shape {x.shape} cannot be split over {n} devices: "
                             f"the leading dimension must be a multiple of {n}")
        spec = PartitionSpec("batch", *([None] * (x.ndim - 1)))
        return jax.device_put(x, NamedSharding(mesh, spec))

    return jax.tree_util.tree_map(put, tree)
