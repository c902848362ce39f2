"""What the imitation actor sees and the data it is fitted on (``twinrl.learn.imitation``).

``make_observer`` builds the observation of ``ImitationConfig.observation`` (the keys the actor
reads, no others); ``episode_coords`` draws an episode's mount pose; ``actor_episodes`` runs an
actor from fresh starts, each from its own pose; ``demonstration_data`` re-simulates the
demonstrations and renders each from ``views_per_state`` poses. ``config`` is an
``ImitationConfig`` throughout; ``imitation`` re-exports these names."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.learn.common import held_episodes
from twinrl.learn.plans import Demonstrations, accurate, smooth_noise

__all__ = ["PROPRIO", "make_observer", "views_per_state", "episode_coords", "actor_episodes",
           "demonstration_data"]

PROPRIO = 14
"""Entries of an arm task's observation a robot measures itself: 7 joint angles, 7 velocities."""


def make_observer(env, config) -> tuple[Callable, object]:
    """``(observe(state, coords) -> observation, obs_spec)`` for ``config.observation``."""
    if config.observation == "state":
        return (lambda s, coords: s.obs), int(env.observation_size)
    if not hasattr(env, "image_observation"):
        raise ValueError(f"observation={config.observation!r} needs a task with a camera mount; "
                         f"{env.name} has none")
    n, o = int(config.image_size or env.config.image_size), (int(env.observation_size),)
    if config.observation == "pose" and not getattr(env, "target_joints", ()):
        raise ValueError(f"observation='pose' needs ArmTask.target_joints; {env.name} has none")
    spec = {"pixels": {"state": (PROPRIO,), "pixels/mount": (n, n, 5)}, "pose": {"estimate": o},
            "target": {"state": (PROPRIO,), "tool": (3,), "target": (7,), "reach": (3,)}
            }[config.observation]
    if not _either(config.proprioception, config.observation != "target"):
        spec.pop("state", None)
    if _either(config.camera_input, config.observation in ("pixels", "target")):
        spec["camera"] = (3,)

    def observe(s, coords):  # only the keys the actor reads: the data set stores no others
        return env.image_observation(s, coords, size=n, keys=tuple(spec))

    return observe, spec


def views_per_state(config) -> int:
    """Mount poses each demonstrated state is rendered from (``ImitationConfig.views``; 1 for
    ``"state"``)."""
    return int(config.views) if config.observation != "state" else 1


def _either(setting: bool | None, default: bool) -> bool:  # camera_input, proprioception
    return default if setting is None else bool(setting)


def episode_coords(env, config, key):
    """An episode's mount pose (pixels; ``config.camera``), a dummy (state): ``train``'s."""
    if config.observation == "state":
        return jnp.zeros(3)
    if config.camera == "default":
        return jnp.asarray(env.mount.default, jnp.float32)
    return jax.random.normal(key, (3,)) * 1.5  # unconstrained coords: spread over the workspace


def actor_episodes(env, observe, act, config, key, n: int, noise: float = 0.0):
    """``held_episodes`` of ``act`` (observation -> action) from ``n`` starts drawn from ``key``,
    each from its own mount pose (``episode_coords``), with smooth action noise ``noise``."""
    ks = jax.vmap(jax.random.split)(jax.random.split(key, n))  # (n, 2): camera, reset
    shake = (smooth_noise(jax.random.fold_in(key, 1), (n, env.episode_length, env.action_size),
                          scale=noise) if noise else None)
    return held_episodes(env, observe, act, ks[:, 1], noise=shake,
                         coords=jax.vmap(lambda k: episode_coords(env, config, k))(ks[:, 0]))


def demonstration_data(env, demos: Demonstrations, config, rng):
    """The demonstrations' (observation, action) pairs, re-simulated (and rendered, from
    ``config.views`` mount poses each), and each pair's weight in the fit (``accurate``)."""
    observe, _ = make_observer(env, config)
    keys, actions = (np.repeat(np.asarray(x), views_per_state(config), axis=0) for x in demos)
    cams = jax.vmap(lambda k: episode_coords(env, config, k))(jax.random.split(rng, len(keys)))
    run = jax.jit(lambda k, a, c: held_episodes(env, observe, None, k, a, c)[:3])
    obs, states, acts = run(jnp.asarray(keys), jnp.asarray(actions), cams)
    flat = lambda x: x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:])  # noqa: E731
    return jax.tree_util.tree_map(flat, obs), flat(acts), flat(accurate(obs, states, env))
