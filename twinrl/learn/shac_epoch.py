"""SHAC's epoch (Xu et al., ICLR 2022, Algorithm 1), the pieces ``twinrl.learn.shac.train``
walks: the train state, the networks and optimisers of one (env, config), the short-horizon
actor loss (Eq. 2), the critic's regression on TD(lambda) targets (Eq. 4-5), Polyak averaging of
the target critic, and the deterministic policy that is deployed. The algorithm, its policy and
its gradient hygiene are described in ``twinrl.learn.shac``; ``config`` here is a
``twinrl.learn.shac.SHACConfig`` (read by field, so this module does not import the trainer).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax
from jax.sharding import PartitionSpec as P

from twinrl.learn.common import tree_where
from twinrl.learn.critic import minibatch_fit, td_lambda_targets
from twinrl.learn.networks import (Network, NetworkConfig, fold_normaliser, init_obs_stats,
                                   make_network, make_value, obs_std, update_obs_stats)
from twinrl.physics.gradients import clip_by_global_norm, global_norm, guard_stats, nan_guard

__all__ = ["SHACState", "make_networks", "Parts", "make_parts", "init_state", "actor_loss",
           "critic_update", "epoch_step", "deployed"]


class SHACState(NamedTuple):
    """Everything a SHAC run carries between epochs (a pytree of arrays of fixed structure)."""

    actor: Any
    """``{"policy": mean-MLP params, "log_std": (action_size,)}``."""
    critic: Any
    """Critic params."""
    target_critic: Any
    """Polyak-averaged critic params (bootstrap values of the actor loss and the targets)."""
    actor_opt: Any
    """Actor optimiser state (NaN-guard counters, clip state, Adam moments)."""
    critic_opt: Any
    """Critic optimiser state."""
    env_state: Any
    """The ``num_envs`` environment states (Brax ``State`` with a leading batch axis)."""
    ep_step: jax.Array
    """(num_envs,) int32: steps taken in each environment's current episode."""
    obs_norm: Any
    """Running observation statistics ``{"mean", "var", "count"}`` (identity if disabled)."""
    rng: jax.Array
    """uint32[2] key: the source of every later random draw."""
    epoch: jax.Array
    """int32: completed epochs."""


def make_networks(obs_size: int, action_size: int, config) -> tuple[Network, Network, Network]:
    """``(policy, policy_pre_tanh, critic)``: the deterministic policy (tanh output, the one
    ``train`` returns), the same MLP without the tanh (the Gaussian's mean), and the critic."""
    pcfg = NetworkConfig(hidden=config.actor_hidden, activation=config.actor_activation,
                         output="tanh")
    policy = make_network(obs_size, action_size, pcfg)
    pre = make_network(obs_size, action_size, dataclasses.replace(pcfg, output="linear"))
    critic = make_value(obs_size, config.critic_hidden, config.critic_activation, layer_norm=True)
    return policy, pre, critic


def _optimizer(lr: float, config, updates: int) -> optax.GradientTransformation:
    if config.lr_schedule == "linear":
        lr = optax.linear_schedule(lr, config.lr_end, max(int(updates), 1))
    return optax.chain(nan_guard(), clip_by_global_norm(config.max_grad_norm),
                       optax.adam(lr, b1=config.adam_b1, b2=config.adam_b2))


class Parts(NamedTuple):
    """What SHAC's pieces share for one (env, config): networks, optimisers, the vmapped env."""

    config: Any
    """The ``SHACConfig``."""
    policy: Network
    """The deterministic policy (tanh output), the one ``train`` returns."""
    pre: Network
    """The same MLP without the tanh: the Gaussian's mean."""
    critic: Network
    actor_tx: optax.GradientTransformation
    critic_tx: optax.GradientTransformation
    v_reset: Callable
    """``jax.vmap(env.reset)``."""
    v_step: Callable
    """``jax.vmap(env.step)``."""
    obs_size: int
    act_size: int
    episode_length: int
    """T, the time limit of training and evaluation episodes."""


def make_parts(env, c) -> Parts:
    """The ``Parts`` of ``env`` under the config ``c``."""
    obs_size, act_size = int(env.observation_size), int(env.action_size)
    policy, pre, critic = make_networks(obs_size, act_size, c)
    return Parts(c, policy, pre, critic, _optimizer(c.actor_lr, c, c.epochs),
                 _optimizer(c.critic_lr, c, c.epochs * c.critic_iterations * c.critic_minibatches),
                 jax.vmap(env.reset), jax.vmap(env.step), obs_size, act_size,
                 int(c.episode_length or env.episode_length))


def init_state(p: Parts, key) -> SHACState:
    """The train state of a fresh run from ``key``."""
    c, N = p.config, int(p.config.num_envs)
    k_pi, k_v, k_env, key = jax.random.split(key, 4)
    actor = {"policy": p.policy.init(k_pi),
             "log_std": jnp.full((p.act_size,), c.init_log_std, jnp.float32)}
    vparams = p.critic.init(k_v)
    return SHACState(
        actor=actor, critic=vparams, target_critic=vparams,
        actor_opt=p.actor_tx.init(actor), critic_opt=p.critic_tx.init(vparams),
        env_state=p.v_reset(jax.random.split(k_env, N)), ep_step=jnp.zeros((N,), jnp.int32),
        obs_norm=init_obs_stats(p.obs_size),
        rng=key, epoch=jnp.zeros((), jnp.int32))


def actor_loss(p: Parts, actor, target_critic, env_state, ep_step, obs_norm, key, part=None):
    """SHAC's short-horizon actor loss (Eq. 2) and the window's data for the critic:
    ``(loss, (next env_state, next ep_step, obs, rewards, next values, boundaries))``.

    ``part = (first, rows)``: ``env_state`` and ``ep_step`` are rows ``first .. first + rows``
    of the ``num_envs`` (one device's share, ``epoch_step``'s ``mesh``); they take those rows
    of the whole batch's random draws, and the loss is their share of the whole batch's."""
    c, N, h, T = p.config, int(p.config.num_envs), int(p.config.horizon), p.episode_length
    k_noise, k_reset = jax.random.split(key)
    keys, noise = jax.random.split(k_reset, N), jax.random.normal(k_noise, (h, N, p.act_size))
    if part is not None:
        first, rows = part
        keys = jax.lax.dynamic_slice_in_dim(keys, first, rows)
        noise = jax.lax.dynamic_slice_in_dim(noise, first, rows, axis=1)
    n = keys.shape[0]
    # One fresh state per environment serves any episode that ends inside this window
    # (h <= T, so at most one ends per window unless the simulation diverges twice).
    fresh = jax.lax.stop_gradient(p.v_reset(keys))
    std = jnp.exp(actor["log_std"])
    mean_o, std_o = obs_norm["mean"], obs_std(obs_norm)
    norm = lambda o: (o - mean_o) / std_o  # noqa: E731

    def step(carry, xs):
        s, t, acc, disc = carry
        eps, i = xs
        a = jnp.tanh(p.pre.apply(actor["policy"], norm(s.obs)) + std * eps)
        s2 = p.v_step(s, a)
        t2 = t + 1
        terminated = s2.done > 0
        ended = terminated | (t2 >= T)
        boundary = ended | (i == h - 1)
        v_next = jnp.where(terminated, 0.0, p.critic.apply(target_critic, norm(s2.obs)))
        acc = acc + disc * s2.reward
        disc = disc * c.gamma
        contrib = jnp.where(boundary, acc + disc * v_next, 0.0)
        acc = jnp.where(boundary, 0.0, acc)
        disc = jnp.where(boundary, 1.0, disc)
        out = (jax.lax.stop_gradient(norm(s.obs)), jax.lax.stop_gradient(s2.reward),
               jax.lax.stop_gradient(v_next), boundary, contrib)
        return (tree_where(ended, fresh, s2), jnp.where(ended, 0, t2), acc, disc), out

    zeros = jnp.zeros((n,))
    (s_end, t_end, _, _), (obs, rew, v_next, bnd, contrib) = jax.lax.scan(
        step, (env_state, ep_step, zeros, jnp.ones((n,))), (noise, jnp.arange(h)))
    loss = -jnp.sum(contrib) / (h * N)
    return loss, (jax.lax.stop_gradient(s_end), t_end, obs, rew, v_next, bnd)


def critic_update(p: Parts, params, opt, obs, targets, key):
    """``critic_iterations`` passes of ``critic_minibatches`` shuffled minibatches regressing the
    critic on the window's targets (SHAC Sec. 3.3, Eq. 4; ``twinrl.learn.critic.minibatch_fit``);
    returns ``(params, opt, last pass's mean loss)``."""
    c, nh = p.config, int(p.config.num_envs) * int(p.config.horizon)
    return minibatch_fit(p.critic.apply, p.critic_tx, params, opt, obs.reshape(nh, p.obs_size),
                         targets.reshape(nh), key, c.critic_iterations, c.critic_minibatches)


def _actor_gradient(p: Parts, mesh, *args):
    """``((loss, aux), gradient)`` of ``actor_loss``; with ``mesh``, each device takes the
    gradient of its environments' share of the loss and the shares are summed once (``psum``)."""
    grad = jax.value_and_grad(lambda *a: actor_loss(p, *a[:-1], part=a[-1]), has_aux=True)
    if mesh is None:
        return grad(*args, None)
    rows = int(p.config.num_envs) // mesh.devices.size

    def local(*args):
        (loss, aux), g = grad(*args, (jax.lax.axis_index("batch") * rows, rows))
        return jax.lax.psum(loss, "batch"), aux, jax.lax.psum(g, "batch")

    env, window, one = P("batch"), P(None, "batch"), P()  # aux: (state, step, obs, rew, v, bnd)
    # check_vma off: the window's scan carries start replicated (zeros) and become per-device
    loss, aux, g = jax.shard_map(
        local, mesh=mesh, in_specs=(one, one, env, env, one, one),
        out_specs=(one, (env, env, window, window, window, window), one), check_vma=False)(*args)
    return (loss, aux), g


def epoch_step(p: Parts, s: SHACState, mesh=None):
    """One epoch of Algorithm 1 (actor, critic, target critic, observation statistics):
    ``(next state, metrics, evaluation key)``.

    ``mesh`` (the environments split over its devices): the actor's gradient is taken per
    device and summed once per epoch. Without it XLA's partitioner sums the gradient over the
    devices at every step of the backward pass through the window (``horizon`` all-reduces an
    epoch): over processes, where each costs milliseconds of TCP, that made two processes
    8.5x slower than one (``bench/scale.py``). None: the one-device program."""
    c = p.config
    key, k_actor, k_critic, k_eval = jax.random.split(s.rng, 4)
    (loss, aux), grads = _actor_gradient(p, mesh, s.actor, s.target_critic, s.env_state,
                                         s.ep_step, s.obs_norm, k_actor)
    env_state, ep_step, obs, rew, v_next, bnd = aux
    updates, actor_opt = p.actor_tx.update(grads, s.actor_opt, s.actor)
    actor = optax.apply_updates(s.actor, updates)

    # Critic targets: the window always ends in a bootstrap (SHAC's done mask at t = h - 1).
    targets = td_lambda_targets(rew, v_next, bnd, c.gamma, c.lam)
    vparams, critic_opt, closs = critic_update(p, s.critic, s.critic_opt, obs, targets, k_critic)
    target = jax.tree_util.tree_map(lambda t, v: c.target_alpha * t
                                    + (1.0 - c.target_alpha) * v, s.target_critic, vparams)
    # The statistics move after the update, so actor and critic always saw one fixed
    # standardisation within a window (the critic's inputs were standardised with it too).
    raw_obs = obs * obs_std(s.obs_norm) + s.obs_norm["mean"]
    obs_norm = update_obs_stats(s.obs_norm, raw_obs) if c.normalize_observations else s.obs_norm
    new = SHACState(actor=actor, critic=vparams, target_critic=target, actor_opt=actor_opt,
                    critic_opt=critic_opt, env_state=env_state, ep_step=ep_step,
                    obs_norm=obs_norm, rng=key, epoch=s.epoch + 1)
    metrics = {
        "grad_norm": global_norm(grads), "actor_loss": loss, "critic_loss": closs,
        "train_reward": jnp.mean(rew), "std": jnp.mean(jnp.exp(actor["log_std"])),
        "skipped": guard_stats(actor_opt)["grad/skipped"],
        "critic_skipped": guard_stats(critic_opt)["grad/skipped"],
    }
    return new, metrics, k_eval


def deployed(s: SHACState):
    """The deterministic policy's params acting on raw observations (normaliser folded in)."""
    return fold_normaliser(s.actor["policy"], s.obs_norm["mean"], obs_std(s.obs_norm))
