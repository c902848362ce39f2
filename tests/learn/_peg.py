"""The short peg insertion and untrained image actor that the sensing tests share."""

import jax

from twinrl import envs
from twinrl.learn.networks import NetworkConfig, make_network

T, PIX = 6, 16
"""Episode length and image size: compiles dominate, so both are small."""


def peg_image_actor():
    """``(env, actor, params)``: peg insertion of ``T`` steps and an untrained actor of its
    state and a ``PIX`` x ``PIX`` mount image."""
    env = envs.make("peg_insertion", episode_length=T)
    spec = {"state": (14,), "pixels/mount": (PIX, PIX, 5)}
    actor = make_network(spec, env.action_size, NetworkConfig(hidden=(16,), output="tanh"))
    return env, actor, actor.init(jax.random.PRNGKey(0))
