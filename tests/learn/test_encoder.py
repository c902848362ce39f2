"""``twinrl.learn.networks``: dict observation specs and the CNN encoder (small 32 x 32 images,
batch 2, to keep compiles short), their checkpoint round trip, and flat specs unchanged."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from twinrl.learn.checkpoint import load_policy, save_policy
from twinrl.learn.networks import MLP, NetworkConfig, check_obs_spec, make_network, make_policy

SPEC = {"state": (3,), "pixels/wrist": (32, 32, 5)}
CFG = NetworkConfig(hidden=(16,), conv_features=(4, 8), conv_kernels=(3, 3), conv_strides=(2, 2),
                    embed=8, output="tanh")


def _obs(key, batch=()):
    k1, k2 = jax.random.split(key)
    return {"state": jax.random.normal(k1, batch + (3,)),
            "pixels/wrist": jax.random.uniform(k2, batch + (32, 32, 5))}


@pytest.fixture(scope="module")
def net():
    net = make_network(SPEC, 2, CFG)
    return net, net.init(jax.random.PRNGKey(0))


def test_dict_spec_output_shapes_single_and_batched(net):
    net, params = net
    assert net.obs_spec == {"pixels/wrist": (32, 32, 5), "state": (3,)}
    assert net.in_size == 3 + 32 * 32 * 5
    one = net.apply(params, _obs(jax.random.PRNGKey(1)))
    assert one.shape == (2,) and np.all(np.abs(np.asarray(one)) <= 1)
    batch = _obs(jax.random.PRNGKey(2), (2,))
    out = net.apply(params, batch)
    assert out.shape == (2, 2)
    # a batch is the same network applied to each observation on its own
    first = net.apply(params, jax.tree.map(lambda x: x[1], batch))
    np.testing.assert_allclose(out[1], first, rtol=1e-5, atol=1e-6)
    # each camera has its own CNN in the params, the state goes straight to the MLP
    enc = params["params"]["encoder"]
    assert {"wrist_conv0", "wrist_conv1", "wrist_dense", "wrist_norm"} == set(enc)
    assert enc["wrist_conv0"]["kernel"].shape == (3, 3, 5, 4)
    assert enc["wrist_dense"]["kernel"].shape == (8 * 8 * 8, 8)   # 32 -> 16 -> 8, 8 channels
    assert params["params"]["head"]["Dense_0"]["kernel"].shape == (3 + 8, 16)


def test_gradient_reaches_the_pixels(net):
    net, params = net
    obs = _obs(jax.random.PRNGKey(3))
    g = jax.grad(lambda px: jnp.sum(net.apply(params, {**obs, "pixels/wrist": px})))(
        obs["pixels/wrist"])
    assert g.shape == (32, 32, 5)
    assert np.all(np.isfinite(np.asarray(g))) and float(jnp.abs(g).max()) > 0


def test_integer_images_are_scaled_to_unit_range(net):
    net, params = net
    obs = _obs(jax.random.PRNGKey(4))
    img = jnp.round(obs["pixels/wrist"] * 255).astype(jnp.uint8)
    as_int = net.apply(params, {**obs, "pixels/wrist": img})
    as_float = net.apply(params, {**obs, "pixels/wrist": img.astype(jnp.float32) / 255})
    np.testing.assert_allclose(as_int, as_float, rtol=1e-5, atol=1e-6)


def test_checkpoint_round_trip_of_a_dict_spec(net, tmp_path):
    net, params = net
    save_policy(tmp_path / "p", net, params, algo="test")
    loaded, lparams, meta = load_policy(tmp_path / "p")
    assert meta["network"]["obs_spec"] == {"pixels/wrist": [32, 32, 5], "state": [3]}
    assert loaded.obs_spec == net.obs_spec and loaded.config == CFG
    obs = _obs(jax.random.PRNGKey(5), (2,))
    np.testing.assert_array_equal(loaded.apply(lparams, obs), net.apply(params, obs))


def test_bad_specs_and_observations_name_the_key(net):
    net, params = net
    cases = [({"state": (3,), "pixels/wrist": (32, 32)}, "'pixels/wrist'"),
             ({"state": (3, 1)}, "'state'"), ({"state": (0,)}, "'state'"),
             ({}, "empty"), (0, "observation size")]
    for spec, word in cases:
        with pytest.raises(ValueError, match=word) as err:
            make_network(spec, 2, CFG)
        assert "\n" not in str(err.value)
    obs = _obs(jax.random.PRNGKey(6))
    bad_obs = [({"pixels/wrist": obs["pixels/wrist"]}, "no key 'state'"),
               ({**obs, "pixels/wrist": obs["pixels/wrist"][:16]}, "'pixels/wrist' has shape"),
               ({**obs, "state": jnp.zeros((2, 3))}, "'state' has batch axes"),
               (obs["state"], "dict observation")]
    for o, word in bad_obs:
        with pytest.raises(ValueError, match=word) as err:
            net.apply(params, o)
        assert "\n" not in str(err.value)
    with pytest.raises(ValueError, match="one entry per convolution"):
        NetworkConfig(conv_features=(4, 8), conv_kernels=(3,))
    with pytest.raises(ValueError, match="NetworkConfig.embed"):
        NetworkConfig(embed=0)


def test_flat_specs_behave_as_before(tmp_path):
    cfg = NetworkConfig(hidden=(8, 8))
    net = make_policy(4, 2, hidden=(8, 8))
    params = net.init(jax.random.PRNGKey(0))
    # the same plain MLP, same parameter tree, as before dict specs existed
    plain = MLP(features=(8, 8), out=2)
    assert jax.tree.structure(params) == jax.tree.structure(
        plain.init(jax.random.PRNGKey(0), jnp.zeros(4)))
    x = jax.random.normal(jax.random.PRNGKey(1), (5, 4))
    np.testing.assert_array_equal(net.apply(params, x), plain.apply(params, x))
    assert net.in_size == 4 and net.obs_spec == 4 and net.config == cfg
    assert check_obs_spec(np.int64(4)) == 4
    with pytest.raises(ValueError, match="size 4"):
        net.apply(params, jnp.zeros((5, 3)))
    save_policy(tmp_path / "p", net, params)
    loaded, lparams, meta = load_policy(tmp_path / "p")
    assert "obs_spec" not in meta["network"] and meta["network"]["in_size"] == 4
    np.testing.assert_array_equal(loaded.apply(lparams, x), net.apply(params, x))
    # a checkpoint written before the encoder fields existed still loads
    old = {k: v for k, v in cfg.to_dict().items() if not k.startswith("conv") and k != "embed"}
    assert NetworkConfig.from_dict(old) == cfg


def test_keypoint_head_reports_where_each_channel_peaks(tmp_path):
    """``image_head="keypoints"``: a spatial softmax per channel hands on each channel's expected
    image position, (x, y) in [-1, 1] -- at a sharp peak, the peak's pixel; the network built
    on it round-trips through a checkpoint and its gradient reaches the pixels."""
    from twinrl.learn.networks import keypoints

    maps = np.zeros((1, 9, 17, 2), np.float32)
    maps[0, 2, 12, 0] = 50.0  # channel 0 peaks at row 2, column 12
    maps[0, 6, 3, 1] = 50.0   # channel 1 at row 6, column 3
    kp = np.asarray(keypoints(jnp.asarray(maps), jnp.zeros(())))
    xs, ys = np.linspace(-1, 1, 17), np.linspace(-1, 1, 9)
    np.testing.assert_allclose(kp[0], [xs[12], xs[3], ys[2], ys[6]], atol=1e-4)
    cfg = NetworkConfig(hidden=(16,), conv_features=(4, 8), conv_kernels=(3, 3),
                        conv_strides=(2, 1), image_head="keypoints", output="tanh")
    net = make_network(SPEC, 2, cfg)
    params = net.init(jax.random.PRNGKey(0))
    obs = _obs(jax.random.PRNGKey(1), (2,))
    assert net.apply(params, obs).shape == (2, 2)
    g = jax.grad(lambda px: net.apply(params, {**obs, "pixels/wrist": px}).sum())(
        obs["pixels/wrist"])
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0
    save_policy(tmp_path / "k", net, params, algo="test")
    loaded, lparams, _ = load_policy(tmp_path / "k")
    assert loaded.config.image_head == "keypoints"
    np.testing.assert_allclose(loaded.apply(lparams, obs), net.apply(params, obs), atol=1e-6)
    with pytest.raises(ValueError, match="image_head must be one of"):
        NetworkConfig(image_head="flat")


def test_rgb_jitter_changes_colours_only_within_its_bounds():
    """The imitation actor's and the sensing Q's augmentation: each image's RGB gets a gain in
    1 +- a and an offset in +- a/2 per channel (clipped to [0, 1]); depth, mask and vector keys
    pass untouched, and different images get different draws."""
    from twinrl.learn.common import rgb_jitter

    obs = _obs(jax.random.PRNGKey(3), (4,))
    out = rgb_jitter(0.1)(obs, jax.random.PRNGKey(4))
    px, new = np.asarray(obs["pixels/wrist"]), np.asarray(out["pixels/wrist"])
    np.testing.assert_array_equal(new[..., 3:], px[..., 3:])
    np.testing.assert_array_equal(out["state"], obs["state"])
    assert new[..., :3].min() >= 0.0 and new[..., :3].max() <= 1.0
    # per image and channel, new = clip(gain * old + bias): recover gain and bias where unclipped
    for b in range(4):
        for c in range(3):
            x, y = px[b, ..., c].ravel(), new[b, ..., c].ravel()
            keep = (y > 1e-6) & (y < 1 - 1e-6)
            gain, bias = np.polyfit(x[keep], y[keep], 1)
            assert abs(gain - 1) <= 0.1 + 1e-4 and abs(bias) <= 0.05 + 1e-4
    assert not np.allclose(new[0, ..., :3] - px[0, ..., :3], new[1, ..., :3] - px[1, ..., :3])


def test_an_ensemble_is_the_mean_of_members_of_their_own_and_survives_a_checkpoint(tmp_path):
    cfg = NetworkConfig(hidden=(16,), conv_features=(4, 8), conv_kernels=(3, 3),
                        conv_strides=(2, 2), embed=8, output="linear", ensemble=3)
    net = make_network(SPEC, 2, cfg)
    params = net.init(jax.random.PRNGKey(0))
    obs = _obs(jax.random.PRNGKey(1), (4,))
    each = np.asarray(net.members(params, obs))
    assert each.shape == (4, 3, 2) and net.apply(params, _obs(jax.random.PRNGKey(1))).shape == (2,)
    np.testing.assert_allclose(net.apply(params, obs), each.mean(axis=1), rtol=1e-5, atol=1e-6)
    assert not np.allclose(each[:, 0], each[:, 1])  # each member from its own initialisation
    save_policy(tmp_path / "p", net, params, algo="test")
    loaded, lparams, _ = load_policy(tmp_path / "p")
    assert loaded.config.ensemble == 3
    np.testing.assert_array_equal(loaded.apply(lparams, obs), net.apply(params, obs))
    assert make_network(3, 1).members is None  # one network: no members
    with pytest.raises(ValueError, match="ensemble"):
        NetworkConfig(ensemble=0)
