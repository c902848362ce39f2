"""Flax networks shared by the trainers: MLP policies and value functions, and a CNN encoder of
camera images in front of them.

A network is described by a small frozen ``NetworkConfig`` (layer sizes, activation, output
squashing), so a checkpoint can rebuild it from JSON without the training code (Brax's habit:
params + a JSON network config). Every trainer builds its networks through ``make_policy`` /
``make_value`` and gets back a ``Network`` of two pure functions, ``init(rng) -> params`` and
``apply(params, obs) -> output``; ``apply`` works on a single observation or any batch of them.

Running observation statistics (``init_obs_stats``, ``update_obs_stats``, ``obs_std``) standardise
a network's inputs while it trains; ``fold_normaliser`` then folds that standardisation into the
first layer, so the deployed network takes raw observations (SHAC's policy).

**Observation specs.** A network's input is described by an *observation spec*: an int (a flat
state vector of that size, every trainer's case so far) or a dict mapping keys to shapes, e.g.
``{"state": (n,), "pixels/wrist": (64, 64, 5)}`` (Brax's vision-network habit). A key starting
with ``pixels/`` is an image ``(H, W, C)``, channels last (RGB, depth, segmentation, ...); every
other key is a vector ``(n,)``. A dict spec puts an ``Encoder`` in front of the MLP: one small CNN
per camera (strided convolutions, then flatten, Dense, LayerNorm, tanh: DrQ-v2's encoder head,
CleanRL's NatureCNN habits sized for 64 x 64 images on a CPU; or, with ``image_head="keypoints"``,
a spatial softmax giving each channel's expected image position), concatenated with the vectors.
``apply`` then takes a dict observation (single, or with the same leading batch axes on every
key); keys the spec does not name are ignored.

The last layer can be initialised to zero (``zero_last=True``): a residual policy
(``twinrl.sim2real.residual``) must output exactly 0 at its first deployment.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping, NamedTuple, Sequence, Union

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from twinrl.learn.common import JSONConfig

__all__ = ["NetworkConfig", "Network", "MLP", "Encoder", "EncodedMLP", "ObsSpec", "is_pixels",
           "check_obs_spec", "spec_size", "make_network", "make_policy", "make_value",
           "ACTIVATIONS", "init_obs_stats", "update_obs_stats", "obs_std", "fold_normaliser",
           "keypoints"]

ACTIVATIONS: dict[str, Callable[[jax.Array], jax.Array]] = {
    "tanh": jnp.tanh, "relu": jax.nn.relu, "elu": jax.nn.elu, "swish": jax.nn.swish,
    "gelu": jax.nn.gelu,
}


@dataclasses.dataclass(frozen=True)
class NetworkConfig(JSONConfig):
    """Architecture of an MLP and, for dict observation specs, of its camera encoder;
    serialisable to JSON (``to_dict`` / ``from_dict``)."""

    hidden: tuple[int, ...] = (64, 64)
    """Hidden layer widths."""
    activation: str = "tanh"
    """Hidden activation, one of ``ACTIVATIONS``."""
    output: str = "tanh"
    """Output squashing: ``"tanh"`` (actions in [-1, 1]) or ``"linear"`` (values, residuals)."""
    layer_norm: bool = False
    """LayerNorm after every hidden layer (SHAC's critic uses it)."""
    zero_last: bool = False
    """Initialise the last layer's kernel and bias to zero, so the output starts at 0."""
    output_scale: float = 1.0
    """Multiplies the output (after squashing): a residual's bound."""

    conv_features: tuple[int, ...] = (16, 32, 32)
    """Channels of each convolution of a camera's CNN (dict observation specs only)."""
    conv_kernels: tuple[int, ...] = (5, 3, 3)
    """Square kernel size of each convolution (as many as ``conv_features``)."""
    conv_strides: tuple[int, ...] = (2, 2, 2)
    """Stride of each convolution ("SAME" padding): (2, 2, 2) takes 64 x 64 images to 8 x 8."""
    embed: int = 64
    """Width of each camera's dense projection (after the convolutions, before LayerNorm)."""
    image_head: str = "dense"
    """What a camera's CNN hands on: ``"dense"`` (flatten, Dense to ``embed``, LayerNorm, tanh)
    or ``"keypoints"`` (a spatial softmax per channel of the last convolution and its expected
    image coordinates: 2 numbers per channel, Levine et al., JMLR 2016 -- where things are, to a
    fraction of a feature cell, which a flattened map localises only coarsely)."""
    ensemble: int = 1
    """Members of a deep ensemble (Lakshminarayanan et al., NeurIPS 2017): that many networks of
    this architecture, each from its own initialisation; ``apply`` is their mean output and
    ``Network.members`` each one's, so a fit can train every member on its own error. 1: one
    network."""

    def __post_init__(self):
        self.check_fields(widths=("hidden", "conv_features", "conv_kernels", "conv_strides"),
                          choices={"activation": ACTIVATIONS, "output": ("tanh", "linear"),
                                   "image_head": ("dense", "keypoints")},
                          positive=("output_scale",), at_least_one=("embed", "ensemble"))
        if not len(self.conv_features) == len(self.conv_kernels) == len(self.conv_strides):
            raise ValueError(f"NetworkConfig: conv_features, conv_kernels and conv_strides must "
                             f"have one entry per convolution, got {self.conv_features}, "
                             f"{self.conv_kernels}, {self.conv_strides}")


class MLP(nn.Module):
    """A plain MLP; ``output`` squashing and zero-initialised last layer as configured."""

    features: Sequence[int]
    out: int
    activation: str = "tanh"
    output: str = "tanh"
    layer_norm: bool = False
    zero_last: bool = False
    output_scale: float = 1.0

    @nn.compact
    def __call__(self, x):
        act = ACTIVATIONS[self.activation]
        for width in self.features:
            x = nn.Dense(width, kernel_init=nn.initializers.lecun_normal())(x)
            if self.layer_norm:
                x = nn.LayerNorm()(x)
            x = act(x)
        last_init = nn.initializers.zeros if self.zero_last else nn.initializers.lecun_normal()
        x = nn.Dense(self.out, kernel_init=last_init, bias_init=nn.initializers.zeros)(x)
        if self.output == "tanh":
            x = jnp.tanh(x)
        return self.output_scale * x


ObsSpec = Union[int, Mapping[str, Sequence[int]]]
"""An int (flat observation size) or a dict of keys to shapes (module docstring)."""


def is_pixels(key: str) -> bool:
    """Whether an observation key names an image ``(H, W, C)``: it starts with ``pixels/``."""
    return key.startswith("pixels/")


def check_obs_spec(spec: ObsSpec) -> int | dict[str, tuple[int, ...]]:
    """``spec`` validated and normalised: an int >= 1, or a dict with sorted keys and tuple
    shapes (``pixels/*`` keys 3-D ``(H, W, C)``, the others 1-D); a bad entry raises a one-line
    ``ValueError`` naming its key."""
    if not isinstance(spec, Mapping):
        if isinstance(spec, bool) or not isinstance(spec, (int, np.integer)) or spec < 1:
            raise ValueError(f"observation size must be an integer >= 1, got {spec!r}")
        return int(spec)
    if not spec:
        raise ValueError("observation spec is an empty dict: name at least one key")
    out = {}
    for key in sorted(spec, key=str):
        shape = spec[key]
        rank = 3 if is_pixels(str(key)) else 1
        ok = isinstance(key, str) and isinstance(shape, (tuple, list)) and len(shape) == rank
        if not ok or not all(isinstance(d, (int, np.integer)) and d >= 1 for d in shape):
            want = "an image shape (H, W, C)" if rank == 3 else "a vector shape (n,)"
            raise ValueError(f"observation spec {key!r}: needs {want} of positive ints, "
                             f"got {shape!r}")
        out[key] = tuple(int(d) for d in shape)
    return out


def spec_size(spec: ObsSpec) -> int:
    """Numbers in one observation of ``spec`` (the flat size, or the sum over a dict's keys)."""
    spec = check_obs_spec(spec)
    if isinstance(spec, int):
        return spec
    return sum(int(np.prod(shape)) for shape in spec.values())


class Encoder(nn.Module):
    """Dict observation -> one feature vector: per ``pixels/*`` key a CNN (``conv_*`` of the
    config, ReLU, "SAME" padding), flattened, projected by Dense to ``embed``, LayerNorm, tanh;
    vector keys pass through; all concatenated in the spec's (sorted) key order. Integer images
    (uint8) are scaled to [0, 1]; float images are taken as they are."""

    spec: tuple[tuple[str, tuple[int, ...]], ...]
    features: Sequence[int]
    kernels: Sequence[int]
    strides: Sequence[int]
    embed: int
    head: str = "dense"

    @nn.compact
    def __call__(self, obs: dict[str, jax.Array]) -> jax.Array:
        parts = []
        for key, shape in self.spec:
            x = obs[key]
            if not is_pixels(key):
                parts.append(x.astype(jnp.float32))
                continue
            name = key.split("/", 1)[1].replace("/", "_")
            batch = x.shape[:x.ndim - 3]
            scale = 1.0 / 255.0 if jnp.issubdtype(x.dtype, jnp.integer) else 1.0
            x = x.astype(jnp.float32).reshape((-1,) + shape) * scale
            for i, (f, k, st) in enumerate(zip(self.features, self.kernels, self.strides)):
                x = jax.nn.relu(nn.Conv(f, (k, k), (st, st), padding="SAME",
                                        name=f"{name}_conv{i}")(x))
            if self.head == "keypoints":
                x = keypoints(x, self.param(f"{name}_log_temperature", nn.initializers.zeros,
                                             ()))
            else:
                x = nn.Dense(self.embed, name=f"{name}_dense")(x.reshape(x.shape[0], -1))
                x = jnp.tanh(nn.LayerNorm(name=f"{name}_norm")(x))
            parts.append(x.reshape(batch + x.shape[-1:]))
        return jnp.concatenate(parts, axis=-1)


def keypoints(x: jax.Array, log_temperature: jax.Array) -> jax.Array:
    """Spatial softmax: ``(B, H, W, C)`` feature maps to ``(B, 2C)`` expected (x, y) image
    coordinates in [-1, 1] of each channel's softmax over the pixels (a learned temperature)."""
    b, h, w, c = x.shape
    logits = x.reshape(b, h * w, c) / jnp.exp(log_temperature)
    p = jax.nn.softmax(logits, axis=1)
    gx, gy = jnp.meshgrid(jnp.linspace(-1.0, 1.0, w), jnp.linspace(-1.0, 1.0, h))
    ex = jnp.einsum("bnc,n->bc", p, gx.reshape(-1))
    ey = jnp.einsum("bnc,n->bc", p, gy.reshape(-1))
    return jnp.concatenate([ex, ey], axis=-1)


class EncodedMLP(nn.Module):
    """``Encoder`` then ``MLP``: the network of a dict observation spec."""

    encoder: Encoder
    head: MLP

    def __call__(self, obs):
        return self.head(self.encoder(obs))


class Network(NamedTuple):
    """Pure functions of a network: ``init(rng) -> params``, ``apply(params, x) -> y``."""

    init: Callable[[jax.Array], Any]
    apply: Callable[[Any, jax.Array], jax.Array]
    in_size: int
    """Numbers in one observation (``spec_size(obs_spec)``)."""
    out_size: int
    config: NetworkConfig
    obs_spec: Any = None
    """The normalised observation spec: an int, or a dict of keys to shapes (None: ``in_size``,
    for networks built elsewhere, e.g. ``twinrl.learn.brax_policies``)."""
    members: Callable[[Any, Any], jax.Array] | None = None
    """An ensemble's (``NetworkConfig.ensemble`` > 1) ``members(params, x) -> (..., ensemble,
    out_size)``: every member's output, whose mean ``apply`` gives; None for one network."""


def _check_dict_obs(spec: dict[str, tuple[int, ...]], obs) -> dict[str, jax.Array]:
    """The spec's keys of a dict observation as arrays, after checking that every key is there
    with the spec's trailing shape and that all share the leading (batch) axes."""
    if not isinstance(obs, Mapping):
        raise ValueError(f"network expects a dict observation with keys {sorted(spec)}, got "
                         f"{type(obs).__name__}")
    out, batch = {}, None
    for key, shape in spec.items():
        if key not in obs:
            raise ValueError(f"observation has no key {key!r} (the network's spec names "
                             f"{sorted(spec)}; got {sorted(obs)})")
        x = jnp.asarray(obs[key])
        lead = x.shape[:x.ndim - len(shape)]
        if x.ndim < len(shape) or x.shape[x.ndim - len(shape):] != shape:
            raise ValueError(f"observation {key!r} has shape {x.shape}, expected (..., "
                             f"{', '.join(map(str, shape))})")
        if batch is not None and lead != batch:
            raise ValueError(f"observation {key!r} has batch axes {lead}, other keys {batch}")
        out[key], batch = x, lead
    return out


def make_network(obs_spec: ObsSpec, out_size: int,
                 config: NetworkConfig = NetworkConfig()) -> Network:
    """A network from observations of ``obs_spec`` to ``R^out_size``.

    An int spec gives a plain MLP whose ``apply`` accepts ``(..., obs_spec)`` arrays; a dict spec
    gives ``Encoder`` + MLP whose ``apply`` accepts dict observations (module docstring)."""
    spec = check_obs_spec(obs_spec)
    if out_size < 1:
        raise ValueError(f"network sizes must be >= 1, got out={out_size}")
    head = MLP(features=config.hidden, out=out_size, activation=config.activation,
               output=config.output, layer_norm=config.layer_norm,
               zero_last=config.zero_last, output_scale=config.output_scale)
    if isinstance(spec, int):
        def init(rng):
            return head.init(rng, jnp.zeros((spec,), jnp.float32))

        def apply(params, x):
            x = jnp.asarray(x)
            if x.shape[-1:] != (spec,):
                raise ValueError(f"network expects inputs of size {spec}, got shape {x.shape}")
            return head.apply(params, x)

        return _ensemble(Network(init, apply, spec, out_size, config, spec))

    module = EncodedMLP(Encoder(tuple(spec.items()), config.conv_features, config.conv_kernels,
                                config.conv_strides, config.embed, config.image_head), head)

    def init_dict(rng):
        return module.init(rng, {k: jnp.zeros(shape, jnp.float32) for k, shape in spec.items()})

    def apply_dict(params, obs):
        return module.apply(params, _check_dict_obs(spec, obs))

    return _ensemble(Network(init_dict, apply_dict, spec_size(spec), out_size, config, spec))


def _ensemble(net: Network) -> Network:
    """``net`` itself, or ``config.ensemble`` copies of it (params stacked on a leading axis)."""
    k = int(net.config.ensemble)
    if k == 1:
        return net

    def init(rng):
        return jax.vmap(net.init)(jax.random.split(rng, k))

    def members(params, x):
        return jnp.moveaxis(jax.vmap(net.apply, in_axes=(0, None))(params, x), 0, -2)

    def apply(params, x):
        return jnp.mean(members(params, x), axis=-2)

    return net._replace(init=init, apply=apply, members=members)


def make_policy(obs_size: ObsSpec, action_size: int, hidden: Sequence[int] = (64, 64),
                activation: str = "tanh") -> Network:
    """A deterministic policy ``obs -> action in [-1, 1]`` (tanh output)."""
    return make_network(obs_size, action_size,
                        NetworkConfig(hidden=tuple(hidden), activation=activation, output="tanh"))


def make_value(obs_size: ObsSpec, hidden: Sequence[int] = (64, 64), activation: str = "elu",
               layer_norm: bool = True) -> Network:
    """A state-value function ``obs -> R`` (``apply`` returns shape ``(...,)``)."""
    net = make_network(obs_size, 1, NetworkConfig(hidden=tuple(hidden), activation=activation,
                                                   output="linear", layer_norm=layer_norm))
    return net._replace(apply=lambda p, x: net.apply(p, x)[..., 0])


# --------------------------------------------------------------------------- observation statistics
def init_obs_stats(size: int) -> dict[str, jax.Array]:
    """Running statistics of ``size``-dimensional observations before any data (unit variance)."""
    return {"mean": jnp.zeros((size,)), "var": jnp.ones((size,)), "count": jnp.full((), 1e-4)}


def update_obs_stats(stats, x):
    """Running observation statistics ``{"mean", "var", "count"}`` updated with the batch ``x``
    (..., d) (Chan et al.'s parallel update of mean and variance)."""
    x = x.reshape(-1, x.shape[-1])
    n, mean, var = x.shape[0], jnp.mean(x, 0), jnp.var(x, 0)
    total = stats["count"] + n
    delta = mean - stats["mean"]
    new_mean = stats["mean"] + delta * n / total
    m2 = stats["var"] * stats["count"] + var * n + jnp.square(delta) * stats["count"] * n / total
    return {"mean": new_mean, "var": m2 / total, "count": total}


def obs_std(stats):
    """The standard deviation a normaliser divides by, from running statistics."""
    # A variance floor of 1e-2: a feature that barely moved so far (cos of a hanging pole) must not
    # blow up to hundreds of standard deviations, and saturate the network, once it does move.
    return jnp.sqrt(stats["var"] + 1e-2)


def fold_normaliser(params, mean: jax.Array, std: jax.Array):
    """MLP params acting on ``(obs - mean) / std`` rewritten to act on raw ``obs``: the first
    Dense layer absorbs the affine map (``W' = W / std``, ``b' = b - (mean / std) W``)."""
    inner = dict(params["params"])
    first = dict(inner["Dense_0"])
    w = first["kernel"]
    first["kernel"] = w / std[:, None]
    first["bias"] = first["bias"] - (mean / std) @ w
    inner["Dense_0"] = first
    return {**params, "params": inner}
