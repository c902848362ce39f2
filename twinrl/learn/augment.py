"""Image augmentations of a minibatch fit (``common.make_minibatch_fit``'s ``augment(obs, key)``).

``random_shift`` is DrQ's (Kostrikov, Yarats & Fergus, "Image augmentation is all you need",
ICLR 2021; Yarats et al., DrQ-v2, 2021): every image is padded by ``pad`` pixels (edges
repeated) and cropped back to its size at a random offset, so a CNN cannot lean on where exactly
in the frame a thing sits -- a few pixels is what a hand-eye calibration's residual and the real
mount's pose error move the image by. All channels of an image (RGB, depth, the target mask)
shift together. ``chain`` applies several augmentations in turn, each with its own key.
``common.rgb_jitter`` is the photometric one."""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp

from twinrl.learn.common import rgb_jitter
from twinrl.learn.networks import is_pixels

__all__ = ["random_shift", "chain", "image_augment"]

Augment = Callable[[Any, jax.Array], Any]


def random_shift(pad: int) -> Augment:
    """``augment(obs, key)``: each ``pixels/*`` image (``(..., H, W, C)``) replaced by its crop
    at a uniform random offset of at most ``pad`` pixels along each axis from the edge-padded
    image (module docstring); one offset per image, the same for all its channels; other keys
    untouched. ``pad`` 0: the identity."""
    pad = int(pad)
    if pad < 0:
        raise ValueError(f"random_shift: pad must be >= 0 pixels, got {pad}")

    def shift_one(img, offset):  # (H, W, C), (2,) in [0, 2 pad]
        h, w, c = img.shape
        padded = jnp.pad(img, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
        return jax.lax.dynamic_slice(padded, (offset[0], offset[1], 0), (h, w, c))

    def augment(obs, key):
        if pad == 0:
            return obs
        out = dict(obs)
        for i, k in enumerate(sorted(k for k in obs if is_pixels(k))):
            x = jnp.asarray(obs[k])
            flat = x.reshape((-1,) + x.shape[-3:])
            offsets = jax.random.randint(jax.random.fold_in(key, i), (flat.shape[0], 2), 0,
                                         2 * pad + 1)
            out[k] = jax.vmap(shift_one)(flat, offsets).reshape(x.shape)
        return out

    return augment


def chain(*augments: Augment | None) -> Augment | None:
    """One ``augment(obs, key)`` applying ``augments`` in order, each with a key of its own
    (``fold_in`` of its position); the ``None`` ones are skipped; None if none is left."""
    steps = [a for a in augments if a is not None]
    if not steps:
        return None
    if len(steps) == 1:
        return steps[0]

    def augment(obs, key):
        for i, a in enumerate(steps):
            obs = a(obs, jax.random.fold_in(key, i))
        return obs

    return augment


def image_augment(rgb_jitter_amount: float, shift: int) -> Augment | None:
    """The fits' augmentation of image observations: ``random_shift(shift)`` then
    ``common.rgb_jitter(rgb_jitter_amount)`` (each skipped at 0); None when both are 0."""
    return chain(random_shift(shift) if shift else None,
                 rgb_jitter(rgb_jitter_amount) if rgb_jitter_amount else None)
