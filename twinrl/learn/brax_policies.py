"""Brax's PPO and APG policies as our ``Network``: what ``twinrl.learn.baselines`` trains and
``twinrl.learn.checkpoint.load_policy`` rebuilds (through ``baselines.NETWORK_KINDS``).

``ppo_policy``/``apg_policy`` wrap Brax's deterministic inference function (the mode of its
tanh-Gaussian, ``tanh(loc)``, after its observation normaliser) on plain-dict params
``{"obs_mean", "obs_std", "policy"}``; the network carries the trainer config's JSON as
``spec``, so a checkpoint rebuilds it without the training code. ``config`` is a
``baselines.PPOConfig`` / ``APGConfig``, read by field (so this module does not import the
trainers, and they import it).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.training.acme import running_statistics
from brax.training.agents.apg import networks as apg_networks
from brax.training.agents.ppo import networks as ppo_networks

from twinrl.learn.networks import ACTIVATIONS, Network, NetworkConfig

__all__ = ["BraxPolicy", "make_ppo_nets", "make_apg_nets", "ppo_policy", "apg_policy"]


def _normaliser(config):
    return running_statistics.normalize if config.normalize_observations else (lambda x, _: x)


def make_ppo_nets(obs_size: int, action_size: int, config):
    """Brax's PPO networks (policy and value) as ``config`` (a ``PPOConfig``) describes them."""
    return ppo_networks.make_ppo_networks(
        obs_size, action_size, preprocess_observations_fn=_normaliser(config),
        policy_hidden_layer_sizes=config.policy_hidden,
        value_hidden_layer_sizes=config.value_hidden,
        activation=ACTIVATIONS[config.activation])


def make_apg_nets(obs_size: int, action_size: int, config):
    """Brax's APG policy network (LayerNorm after each layer) as ``config`` (an ``APGConfig``)
    describes it."""
    return apg_networks.make_apg_networks(
        obs_size, action_size, preprocess_observations_fn=_normaliser(config),
        hidden_layer_sizes=config.policy_hidden, activation=ACTIVATIONS[config.activation],
        layer_norm=True)


class BraxPolicy(Network):
    """A ``Network`` that also carries ``spec``, the JSON ``twinrl.learn.checkpoint`` saves and
    ``load_policy`` rebuilds it from (``{"kind": "brax_ppo" | "brax_apg", "in_size", "out_size",
    "config": <the trainer config as a dict>}``)."""

    # No __slots__: instances get a __dict__ for ``spec``.


def _as_network(kind, nets, make_inference, obs_size, action_size, config,
                layer_norm) -> Network:
    """Brax's deterministic inference function as our ``Network`` on plain-dict params."""
    make_policy = make_inference(nets)

    def apply(params, obs):
        obs = jnp.asarray(obs, jnp.float32)
        if obs.shape[-1] != obs_size:
            raise ValueError(f"policy expects observations of size {obs_size}, got {obs.shape}")
        norm = running_statistics.NestedMeanStd(mean=params["obs_mean"], std=params["obs_std"])
        # Brax's inference fns take (normaliser, policy[, value]) and a key the mode ignores.
        act, _ = make_policy((norm, params["policy"]), deterministic=True)(
            obs, jax.random.PRNGKey(0))
        return act

    def init(rng):
        return {"obs_mean": jnp.zeros((obs_size,)), "obs_std": jnp.ones((obs_size,)),
                "policy": nets.policy_network.init(rng)}

    cfg = NetworkConfig(hidden=config.policy_hidden, activation=config.activation,
                        output="tanh", layer_norm=layer_norm)
    net = BraxPolicy(init, apply, obs_size, action_size, cfg)
    net.spec = {"kind": kind, "in_size": obs_size, "out_size": action_size,
                "config": config.to_dict()}
    return net


def ppo_policy(obs_size: int, action_size: int, config) -> Network:
    """The deterministic PPO policy ``obs -> tanh(loc)`` for params saved by ``ppo_train``."""
    return _as_network("brax_ppo", make_ppo_nets(obs_size, action_size, config),
                       ppo_networks.make_inference_fn, obs_size, action_size, config, False)


def apg_policy(obs_size: int, action_size: int, config) -> Network:
    """The deterministic APG policy ``obs -> tanh(loc)`` for params saved by ``apg_train``."""
    return _as_network("brax_apg", make_apg_nets(obs_size, action_size, config),
                       apg_networks.make_inference_fn, obs_size, action_size, config, True)
