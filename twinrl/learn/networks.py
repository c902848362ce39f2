"""Flax networks shared by the trainers: MLP policies and value functions.

A network is described by a small frozen ``NetworkConfig`` (layer sizes, activation, output
squashing), so a checkpoint can rebuild it from JSON without the training code (Brax's habit:
params + a JSON network config). Every trainer builds its networks through ``make_policy`` /
``make_value`` and gets back a ``Network`` of two pure functions, ``init(rng) -> params`` and
``apply(params, obs) -> output``; ``apply`` works on a single observation or any batch of them.

Running observation statistics (``init_obs_stats``, ``update_obs_stats``, ``obs_std``) standardise
a network's inputs while it trains; ``fold_normaliser`` then folds that standardisation into the
first layer, so the deployed network takes raw observations (SHAC's policy).

The last layer can be initialised to zero (``zero_last=True``): a residual policy
(``twinrl.sim2real.residual``) must output exactly 0 at its first deployment.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

__all__ = ["NetworkConfig", "Network", "MLP", "make_network", "make_policy", "make_value",
           "ACTIVATIONS", "init_obs_stats", "update_obs_stats", "obs_std", "fold_normaliser"]

ACTIVATIONS: dict[str, Callable[[jax.Array], jax.Array]] = {
    "tanh": jnp.tanh, "relu": jax.nn.relu, "elu": jax.nn.elu, "swish": jax.nn.swish,
    "gelu": jax.nn.gelu,
}


@dataclasses.dataclass(frozen=True)
class NetworkConfig:
    """Architecture of an MLP, serialisable to JSON (``dataclasses.asdict``)."""

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

    def __post_init__(self):
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        if any(h < 1 for h in self.hidden):
            raise ValueError(f"hidden layer widths must be >= 1, got {self.hidden}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, "
                             f"got {self.activation!r}")
        if self.output not in ("tanh", "linear"):
            raise ValueError(f"output must be 'tanh' or 'linear', got {self.output!r}")
        if not self.output_scale > 0:
            raise ValueError(f"output_scale must be > 0, got {self.output_scale}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "NetworkConfig":
        return cls(**{**d, "hidden": tuple(d.get("hidden", cls.hidden))})


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


class Network(NamedTuple):
    """Pure functions of a network: ``init(rng) -> params``, ``apply(params, x) -> y``."""

    init: Callable[[jax.Array], Any]
    apply: Callable[[Any, jax.Array], jax.Array]
    in_size: int
    out_size: int
    config: NetworkConfig


def make_network(in_size: int, out_size: int, config: NetworkConfig = NetworkConfig()) -> Network:
    """An MLP ``R^in_size -> R^out_size``; ``apply`` accepts ``(..., in_size)`` inputs."""
    if in_size < 1 or out_size < 1:
        raise ValueError(f"network sizes must be >= 1, got in={in_size}, out={out_size}")
    module = MLP(features=config.hidden, out=out_size, activation=config.activation,
                 output=config.output, layer_norm=config.layer_norm,
                 zero_last=config.zero_last, output_scale=config.output_scale)

    def init(rng):
        return module.init(rng, jnp.zeros((in_size,), jnp.float32))

    def apply(params, x):
        x = jnp.asarray(x)
        if x.shape[-1] != in_size:
            raise ValueError(f"network expects inputs of size {in_size}, got shape {x.shape}")
        return module.apply(params, x)

    return Network(init, apply, in_size, out_size, config)


def make_policy(obs_size: int, action_size: int, hidden: Sequence[int] = (64, 64),
                activation: str = "tanh") -> Network:
    """A deterministic policy ``obs -> action in [-1, 1]`` (tanh output)."""
    return make_network(obs_size, action_size,
                        NetworkConfig(hidden=tuple(hidden), activation=activation, output="tanh"))


def make_value(obs_size: int, hidden: Sequence[int] = (64, 64), activation: str = "elu",
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
