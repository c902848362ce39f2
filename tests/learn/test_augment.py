"""DrQ's random shift and the chaining of the fits' image augmentations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl.learn.augment import chain, image_augment, random_shift


def _images(shape=(6, 16, 16, 5)):
    return jax.random.uniform(jax.random.PRNGKey(0), shape)


def test_a_shifted_image_keeps_its_shape_and_other_keys_are_untouched():
    obs = {"pixels/mount": _images((2, 3, 16, 16, 5)), "state": jnp.arange(6.0).reshape(2, 3, 1)}
    out = random_shift(4)(obs, jax.random.PRNGKey(1))
    assert out["pixels/mount"].shape == obs["pixels/mount"].shape
    np.testing.assert_array_equal(out["state"], obs["state"])


def test_the_shift_is_a_crop_of_the_edge_padded_image_within_pad_pixels():
    pad, x = 3, _images()
    out = np.asarray(random_shift(pad)({"pixels/a": x}, jax.random.PRNGKey(2))["pixels/a"])
    padded = np.pad(np.asarray(x), ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="edge")
    offsets = []
    for i in range(x.shape[0]):
        found = [(dy, dx) for dy in range(2 * pad + 1) for dx in range(2 * pad + 1)
                 if np.array_equal(padded[i, dy:dy + 16, dx:dx + 16], out[i])]
        assert found, f"image {i} is no crop of its padded image within {pad} pixels"
        offsets.append(found[0])
    assert len(set(offsets)) > 1  # the images of a batch are shifted differently


def test_the_shift_is_a_function_of_its_key():
    obs, aug = {"pixels/a": _images()}, random_shift(4)
    a, b = (aug(obs, jax.random.PRNGKey(7))["pixels/a"] for _ in range(2))
    np.testing.assert_array_equal(a, b)
    c = aug(obs, jax.random.PRNGKey(8))["pixels/a"]
    assert not np.array_equal(a, c)


def test_no_shift_and_no_jitter_is_no_augmentation():
    x = {"pixels/a": _images()}
    assert random_shift(0)(x, jax.random.PRNGKey(0)) is x
    assert image_augment(0.0, 0) is None and chain(None, None) is None
    with pytest.raises(ValueError, match="pad"):
        random_shift(-1)


def test_the_chain_shifts_then_jitters_with_keys_of_its_own():
    obs = {"pixels/a": _images()}
    both = image_augment(0.1, 2)(obs, jax.random.PRNGKey(3))["pixels/a"]
    assert both.shape == obs["pixels/a"].shape
    # depth and mask are shifted, never jittered: they are a crop of the padded originals
    shifted = random_shift(2)(obs, jax.random.fold_in(jax.random.PRNGKey(3), 0))["pixels/a"]
    np.testing.assert_array_equal(both[..., 3:], shifted[..., 3:])
    assert not np.array_equal(both[..., :3], shifted[..., :3])


def test_the_fits_configs_take_a_shift_and_refuse_a_negative_one():
    from twinrl.learn.imitation import ImitationConfig
    from twinrl.learn.sensing import SensingConfig

    for cls in (ImitationConfig, SensingConfig):
        assert cls(random_shift=4).random_shift == 4
        with pytest.raises(ValueError, match="random_shift"):
            cls(random_shift=-1)
