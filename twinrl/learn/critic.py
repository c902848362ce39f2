"""One TD(lambda) critic for the gradient learners (SHAC, PODS and HDS with ``critic=True``).

SHAC (Xu et al., ICLR 2022, Sec. 3.3) fits a state value ``V(obs)`` of the policy to TD(lambda)
targets (Eq. 5) and bootstraps the short-horizon actor objective with it (Eq. 2); PODS and HDS use
the same value to close each trajopt window (``twinrl.learn.pods``, "Critic"). The targets
(``td_lambda_targets``), their form over a batch of truncated rollouts (``critic_targets``) and the
two fits live here once: full-batch Adam steps for PODS/HDS (``make_critic_update``, the policy
regression of ``twinrl.learn.common.make_regress`` with a one-output network) and SHAC's shuffled
minibatch passes (``minibatch_fit``). The sensing Q of SAM-RL is meant to reuse the targets.
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import optax

from twinrl.learn.common import make_optimizer, make_regress
from twinrl.learn.networks import Network, make_value

__all__ = ["td_lambda_targets", "critic_targets", "make_critic_update", "make_critic",
           "make_terminal_fn", "critic_stats", "minibatch_fit"]


def td_lambda_targets(rewards: jax.Array, next_values: jax.Array, boundaries: jax.Array,
                      gamma: float, lam: float) -> jax.Array:
    """TD(lambda) value targets over a window (SHAC Sec. 3.3, Eq. 5), time on axis 0.

    ``rewards[t]`` is earned by the step from ``s_t`` to ``s_{t+1}``, ``next_values[t]`` is the
    (target) value of ``s_{t+1}`` (already 0 where the episode terminated), and ``boundaries[t]``
    is true where the return cannot be followed past ``s_{t+1}`` (the episode ended there, or the
    window does). The recursion
    ``G_t = r_t + gamma * ((1 - lambda) V(s_{t+1}) + lambda G_{t+1})`` with ``G_t = r_t + gamma
    V(s_{t+1})`` at a boundary weighs the n-step returns ``(1 - lambda) lambda^(n-1)`` and gives the
    longest one available the remaining weight. Any trailing shape (e.g. environments) is kept.
    """
    rewards, next_values = jnp.asarray(rewards), jnp.asarray(next_values)
    boundaries = jnp.asarray(boundaries, bool)
    if not (rewards.shape == next_values.shape == boundaries.shape):
        raise ValueError(f"rewards {rewards.shape}, next_values {next_values.shape} and "
                         f"boundaries {boundaries.shape} must have the same shape")

    def back(g_next, x):
        r, v, b = x
        g = r + gamma * jnp.where(b, v, (1.0 - lam) * v + lam * g_next)
        return g, g

    _, g = jax.lax.scan(back, jnp.zeros_like(rewards[-1]), (rewards, next_values, boundaries),
                        reverse=True)
    return g


def critic_targets(value_fn: Callable, obs, rewards, valid, final_obs, final_valid,
                   gamma: float, lam: float) -> jax.Array:
    """TD(lambda) targets (B, T) of the value of each visited state (SHAC Sec. 3.3, Eq. 5;
    ``td_lambda_targets``) from rollouts (B, T) of the policy.

    ``value_fn(obs) -> (...,)`` is the critic before this epoch's update. The rollout is
    truncated, not terminated, at its last step: the return is followed past it with
    ``V(final_obs)``; a state that is not live (the simulation diverged) is worth 0.
    """
    v = value_fn(jnp.where(valid[..., None], obs, 0.0))
    v_final = value_fn(jnp.where(final_valid[..., None], final_obs, 0.0))
    next_v = jnp.concatenate([v[:, 1:], v_final[:, None]], axis=1)
    next_ok = jnp.concatenate([valid[:, 1:], final_valid[:, None]], axis=1)
    next_v = jnp.where(next_ok, next_v, 0.0)
    last = jnp.arange(valid.shape[1]) == valid.shape[1] - 1
    boundaries = ~next_ok | last[None, :]
    g = td_lambda_targets(jnp.where(valid, rewards, 0.0).T, next_v.T, boundaries.T, gamma, lam)
    return jax.lax.stop_gradient(g.T)


def make_critic_update(value_apply: Callable, optimizer, steps: int, gamma: float, lam: float):
    """``update(critic_params, opt_state, obs (B, T, o), rewards, valid (B, T), final_obs (B, o),
    final_valid (B,)) -> (critic_params, opt_state, loss_before, loss_after)``: TD(lambda) targets
    from the current critic, then ``steps`` full-batch Adam steps on the squared error of the
    valid states (``make_regress``, the policy's regression, with a one-output network)."""
    regress = make_regress(lambda p, x: value_apply(p, x)[..., None], optimizer, steps)

    def update(cparams, opt_state, obs, rewards, valid, final_obs, final_valid):
        targets = critic_targets(lambda o: value_apply(cparams, o), obs, rewards, valid,
                                 final_obs, final_valid, gamma, lam)
        p, s, loss_after, _, loss_before = regress(cparams, opt_state, obs, targets, valid)
        return p, s, loss_before, loss_after

    return update


def make_critic(env, c) -> tuple[Network, optax.GradientTransformation, Callable | None]:
    """``(critic, critic_optimizer, critic_update or None)`` of a PODS-family config ``c``
    (its ``critic*``, ``gamma`` and ``lam`` fields; the update is None when ``c.critic`` is
    off, the network and optimiser exist either way so the train state keeps one structure)."""
    critic = make_value(env.observation_size, c.critic_hidden, "elu", layer_norm=True)
    optimizer = make_optimizer(c.critic_learning_rate, None)
    update = (make_critic_update(critic.apply, optimizer, c.critic_steps, c.gamma, c.lam)
              if c.critic else None)
    return critic, optimizer, update


def make_terminal_fn(env, value_apply: Callable, cparams) -> Callable:
    """``s_T -> V(observe(s_T))`` on ``trajopt``'s state vector ``concat(qpos, qvel)``."""
    nq = env.sim.nq
    return lambda s: value_apply(cparams, env.observe(s[:nq], s[nq:]))


def critic_stats(batch, critic: bool) -> dict[str, float]:
    """The critic's per-epoch figures (none without a critic)."""
    if not critic:
        return {}
    return {"value_loss": float(batch.value_loss),
            "value_loss_before": float(batch.value_loss_before), "value": float(batch.value)}


def minibatch_fit(apply_fn: Callable, tx: optax.GradientTransformation, params, opt_state, obs,
                  targets, key, iterations: int, minibatches: int):
    """``iterations`` passes of ``minibatches`` shuffled minibatches regressing
    ``apply_fn(params, obs)`` on ``targets`` (SHAC Sec. 3.3, Eq. 4; ``obs`` (n, o), ``targets``
    (n,)); returns ``(params, opt_state, last pass's mean loss)``."""
    n = targets.shape[0]

    def loss_fn(q, o, y):
        return jnp.mean(jnp.square(apply_fn(q, o) - y))

    def minibatch(carry, idx):
        q, s = carry
        loss, grad = jax.value_and_grad(loss_fn)(q, obs[idx], targets[idx])
        u, s = tx.update(grad, s, q)
        return (optax.apply_updates(q, u), s), loss

    def one_pass(carry, k):
        perm = jax.random.permutation(k, n).reshape(minibatches, -1)
        return jax.lax.scan(minibatch, carry, perm)

    (params, opt_state), losses = jax.lax.scan(one_pass, (params, opt_state),
                                               jax.random.split(key, iterations))
    return params, opt_state, jnp.mean(losses[-1])
