"""Gradient hygiene for learning through a simulator, as small composable transforms.

Gradients through long rollouts explode (the Hybrid Differentiable Simulation study saw norms blow
up past a horizon of ~50 steps; SHAC, Xu et al. ICLR 2022 Sec. 3, truncates its horizon for the
same reason) and through contacts they can turn non-finite. Three remedies, each usable alone:

- **truncation windows** — ``truncate(state, t, every)`` stops the gradient through the carried
  state every ``every`` steps inside a scan (``Sim.rollout(..., truncate=k)`` uses it);
- **global-norm clipping** — ``clip_by_global_norm(max_norm)``;
- **NaN/inf guard** — ``nan_guard()`` zeroes a whole update if any entry is non-finite and counts it.

The two update transforms are ``optax.GradientTransformation``s, so they chain with an optimiser:
``optax.chain(nan_guard(), clip_by_global_norm(1.0), optax.adam(1e-3))``; ``hygiene(...)`` builds
the usual pair. The guard goes first so that a NaN never reaches the clipping norm, the optimiser
moments, or the parameters. ``guard_stats(opt_state)`` reads the counters back for logging.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

__all__ = [
    "truncate", "global_norm", "all_finite", "nan_guard", "NanGuardState",
    "clip_by_global_norm", "ClipState", "hygiene", "guard_stats",
]


def truncate(state, t: jax.Array, every: int | None):
    """Stop gradients through ``state`` when ``t`` is a multiple of ``every`` (None: never)."""
    if not every:
        return state
    if every < 1:
        raise ValueError(f"truncation window must be >= 1 step, got {every}")
    return jax.lax.cond(t % every == 0, jax.lax.stop_gradient, lambda s: s, state)


def global_norm(tree) -> jax.Array:
    """L2 norm over every leaf of a pytree."""
    leaves = [jnp.sum(jnp.square(x)) for x in jax.tree_util.tree_leaves(tree)]
    return jnp.sqrt(sum(leaves)) if leaves else jnp.zeros(())


def all_finite(tree) -> jax.Array:
    """True when no leaf holds a NaN or inf."""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.array(True)


class NanGuardState(NamedTuple):
    skipped: jax.Array
    """Number of updates zeroed because they held a non-finite value."""
    total: jax.Array
    """Number of updates seen."""


def nan_guard() -> optax.GradientTransformation:
    """Zero the whole update when any entry is NaN or inf, and count it."""

    def init(params):
        del params
        return NanGuardState(skipped=jnp.zeros((), jnp.int32), total=jnp.zeros((), jnp.int32))

    def update(updates, state, params=None):
        del params
        ok = all_finite(updates)
        # where() rather than multiplication: 0 * NaN is NaN.
        updates = jax.tree_util.tree_map(lambda u: jnp.where(ok, u, jnp.zeros_like(u)), updates)
        return updates, NanGuardState(skipped=state.skipped + (~ok).astype(jnp.int32),
                                      total=state.total + 1)

    return optax.GradientTransformation(init, update)


class ClipState(NamedTuple):
    last_norm: jax.Array
    """Global norm of the last update before clipping (for logging)."""
    clipped: jax.Array
    """Number of updates that were scaled down."""


def clip_by_global_norm(max_norm: float) -> optax.GradientTransformation:
    """Scale the update so its global norm is at most ``max_norm``; remembers the raw norm."""
    if not max_norm > 0:
        raise ValueError(f"max_norm must be > 0, got {max_norm}")

    def init(params):
        del params
        return ClipState(last_norm=jnp.zeros(()), clipped=jnp.zeros((), jnp.int32))

    def update(updates, state, params=None):
        del params
        norm = global_norm(updates)
        scale = jnp.where(norm > max_norm, max_norm / jnp.maximum(norm, 1e-30), 1.0)
        updates = jax.tree_util.tree_map(lambda u: (u * scale).astype(u.dtype), updates)
        return updates, ClipState(last_norm=norm, clipped=state.clipped + (norm > max_norm))

    return optax.GradientTransformation(init, update)


def hygiene(max_norm: float | None = 1.0) -> optax.GradientTransformation:
    """NaN guard, then (optionally) global-norm clipping. Chain an optimiser after it."""
    parts = [nan_guard()]
    if max_norm is not None:
        parts.append(clip_by_global_norm(max_norm))
    return optax.chain(*parts)


def guard_stats(opt_state) -> dict[str, jax.Array]:
    """Counters of every guard/clip state found in an optax state tree (for metrics)."""
    out: dict[str, jax.Array] = {}

    def visit(s):
        if isinstance(s, NanGuardState):
            out["grad/skipped"] = s.skipped
            out["grad/updates"] = s.total
        elif isinstance(s, ClipState):
            out["grad/norm"] = s.last_norm
            out["grad/clipped"] = s.clipped
        elif isinstance(s, (tuple, list)):
            for x in s:
                visit(x)

    visit(opt_state)
    return out
