"""The PODS family's epoch (PODS, Mora et al. ICML 2021, Sec. 4 and Algorithm 1; also HDS's):
sample policy rollouts cut into trajopt windows, improve every window, regress the policy.

``twinrl.learn.pods`` explains the method (windows, horizon, critic, how ``env_steps`` count);
``twinrl.learn.hds`` adds exploration noise, an annealed step size and rollouts through a learned
model. What both run lives here: ``rollout_windows`` (a rollout kept at every window start),
``improve_window`` (``trajopt``'s improvement of one window), ``make_sample_improve`` (steps 1-2
for a batch, vmapped and sharded, the critic fitted between them), ``compile_parts`` (every jitted
piece of a config: ``Compiled``), ``init_state`` and ``epoch_update`` (steps 1-3 of one epoch), and
``window_stats`` (the improvement's per-epoch figures).
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from twinrl.learn import trajopt
from twinrl.learn.common import make_evaluator, make_optimizer, make_regress, raw_key
from twinrl.learn.critic import make_critic, make_terminal_fn
from twinrl.learn.networks import Network, make_policy
from twinrl.learn.trainer import replicate
from twinrl.physics.parallel import shard_batch

__all__ = ["Windows", "rollout_windows", "state_problem", "window_stats", "improve_window",
           "Batch", "make_sample_improve", "Compiled", "compile_parts", "init_state",
           "epoch_update"]


class Windows(NamedTuple):
    """A policy rollout cut into W windows of H steps (leading axes (W, H) unless noted)."""

    starts: Any
    """The ``State`` at each window's start (leading axis W)."""
    obs: jax.Array
    """Observation before each action (W, H, obs)."""
    actions: jax.Array
    """Executed actions (W, H, m)."""
    valid: jax.Array
    """True where the state before the action was live and finite (W, H)."""
    rewards: jax.Array
    """Reward of each step, 0 after the episode ended (W, H)."""
    final_obs: jax.Array | None = None
    """Observation of the state after the last step (obs,): the critic bootstraps there."""
    final_valid: jax.Array | None = None
    """True if that state is live and finite ()."""


def rollout_windows(step_fn: Callable, apply_fn: Callable, params, state0, windows: int,
                    horizon: int, noise: jax.Array | None = None) -> Windows:
    """Roll the policy out from ``state0`` for ``windows * horizon`` steps with ``step_fn``
    (``env.step`` or a drop-in model), keeping the state at every window start.

    ``noise`` (W, H, m), if given, is added to the policy's action before clipping to [-1, 1]
    (HDS's exploration).
    """
    m = apply_fn(params, state0.obs).shape[-1]
    if noise is None:
        noise = jnp.zeros((windows, horizon, m), jnp.float32)

    def inner(s, eps):
        a = jnp.clip(apply_fn(params, s.obs) + eps, -1.0, 1.0)
        s2 = step_fn(s, a)
        valid = (s.done == 0) & jnp.all(jnp.isfinite(s.obs))
        return s2, (s.obs, a, valid, jnp.where(s.done > 0, 0.0, s2.reward))

    def outer(s, eps_w):
        s_end, data = jax.lax.scan(inner, s, eps_w)
        return s_end, (s, data)

    s_end, (starts, (obs, actions, valid, rewards)) = jax.lax.scan(outer, state0, noise)
    final_valid = (s_end.done == 0) & jnp.all(jnp.isfinite(s_end.obs))
    return Windows(starts, obs, actions, valid, rewards, s_end.obs, final_valid)


def state_problem(env, step_fn: Callable, state) -> tuple[trajopt.RolloutFn, trajopt.RewardFn]:
    """``trajopt``'s ``(rollout_fn, reward_fn)`` from ``state`` through any drop-in ``step_fn(state,
    action) -> State`` (HDS's learned dynamics): the state vector is the ``pipeline_state``'s
    ``concat(qpos, qvel)`` and the reward is the task's ``env.reward`` of it, as in
    ``trajopt.env_problem``."""
    nq = env.sim.nq

    def rollout_fn(actions):
        def body(s, a):
            s = step_fn(s, a)
            d = s.pipeline_state
            return s, jnp.concatenate([d.qpos, d.qvel], axis=-1)
        return jax.lax.scan(body, state, actions)[1]

    def reward_fn(s, a):
        return env.reward(s[:nq], s[nq:], a)[0]

    return rollout_fn, reward_fn


def window_stats(res: trajopt.TrajoptResult) -> dict[str, float]:
    """Per-epoch figures of the improvement step over all windows (first iteration's gradient)."""
    gn = np.asarray(res.grad_norm, np.float64)
    fin = np.isfinite(gn)
    acc = np.asarray(res.accepted, bool)
    alpha = np.asarray(res.alpha, np.float64)
    return {
        "grad_norm": float(gn[fin].mean()) if fin.any() else float("nan"),
        "accepted_frac": float(acc.mean()),
        "improvement": float(np.mean(np.asarray(res.value, np.float64)
                                     - np.asarray(res.old_value, np.float64))),
        "alpha": float(alpha[acc].mean()) if acc.any() else 0.0,
        "nonfinite": float(np.asarray(res.nonfinite).sum()),
    }


def improve_window(problem, actions, config: trajopt.TrajoptConfig, iterations: int,
                   terminal_fn: trajopt.TerminalFn | None = None,
                   direction_scale: jax.Array | float = 1.0) -> trajopt.TrajoptResult:
    """``iterations`` trajopt steps of one window as one result: the first step's gradient norm
    and starting value, the last step's actions and value, accepted if any step was
    (``terminal_fn`` and ``direction_scale`` as in ``trajopt.improve``)."""
    if iterations == 1:
        return trajopt.improve(*problem, actions, config, terminal_fn, direction_scale)
    _, h = trajopt.optimize(*problem, actions, config, iterations, terminal_fn, direction_scale)
    return trajopt.TrajoptResult(
        actions=h.actions[-1], value=h.value[-1], old_value=h.old_value[0], alpha=h.alpha[-1],
        accepted=jnp.any(h.accepted), grad_norm=h.grad_norm[0], nonfinite=jnp.max(h.nonfinite),
        env_steps=jnp.sum(h.env_steps))


class Batch(NamedTuple):
    """One epoch's improved rollouts, batch-major: regression data and per-window results."""

    obs: jax.Array
    """(B, W, H, obs) states the policy visited."""
    targets: jax.Array
    """(B, W, H, m) improved actions (the executed ones where not accepted)."""
    weights: jax.Array
    """(B, W, H) 1 where the pair is a regression target (accepted window, live finite state)."""
    result: trajopt.TrajoptResult
    """Per-window results (B, W)."""
    rollout_return: jax.Array
    """(B,) return of each executed rollout."""
    value_loss: jax.Array = None
    """() critic loss after this epoch's fit (0 without a critic)."""
    value_loss_before: jax.Array = None
    """() critic loss on the fresh targets before the fit (0 without a critic)."""
    value: jax.Array = None
    """() mean critic value of the visited states after the fit (0 without a critic)."""


def make_sample_improve(env, apply_fn, windows: int, horizon: int, batch_size: int,
                        improve_fn: Callable, *, dynamics: Callable | None = None,
                        n_model: int = 0, noisy: bool = False, value_apply: Callable | None = None,
                        critic_update: Callable | None = None) -> Callable:
    """A jitted ``sample_improve(params, keys (B, 2), sigma, scales (B,), critic_params,
    critic_opt_state) -> (Batch, critic_params, critic_opt_state)``: steps 1-2 of the module
    docstring for a batch of start keys (sharded over devices by the caller), with the critic
    fitted between them when ``critic_update`` is given (its state passes through otherwise).

    ``improve_fn(problem, actions, scale, terminal_fn) -> TrajoptResult`` improves one window;
    ``scale`` is the rollout's entry of ``scales`` (HDS's annealed step size; PODS ignores it) and
    ``terminal_fn`` the critic's value of the window's last state (None without a critic). The
    last ``n_model`` rollouts run through ``dynamics`` instead of ``env.step`` (HDS's model
    fraction). ``sigma`` is the exploration noise's standard deviation when ``noisy``.
    """
    m = env.action_size
    W, H = int(windows), int(horizon)

    def one(step_fn, params, key, sigma):
        k_reset, k_noise = jax.random.split(key)
        s0 = env.reset(k_reset)
        noise = sigma * jax.random.normal(k_noise, (W, H, m)) if noisy else None
        return rollout_windows(step_fn, apply_fn, params, s0, W, H, noise)

    def sample_improve(params, keys, sigma, scales, cparams, copt):
        n_env = batch_size - n_model
        # (step_fn, problem_fn, slice of the batch) of each part
        parts = []
        if n_env:
            parts.append((env.step, lambda s: trajopt.env_problem(env, s), slice(0, n_env)))
        if n_model:
            parts.append((dynamics, lambda s: state_problem(env, dynamics, s),
                          slice(n_env, batch_size)))
        wins = [jax.vmap(lambda k: one(step_fn, params, k, sigma))(keys[sl])
                for step_fn, _, sl in parts]
        cat = lambda xs: jax.tree_util.tree_map(lambda *x: jnp.concatenate(x, 0), *xs)  # noqa: E731
        win = cat([w._replace(starts=None) for w in wins])
        zero = jnp.zeros((), jnp.float32)
        vloss0 = vloss = vmean = zero
        terminal_fn = None
        if critic_update is not None:
            B = win.obs.shape[0]
            flat = lambda x: x.reshape((B, W * H) + x.shape[3:])  # noqa: E731
            cparams, copt, vloss0, vloss = critic_update(
                cparams, copt, flat(win.obs), flat(win.rewards), flat(win.valid), win.final_obs,
                win.final_valid)
            vmean = jnp.mean(value_apply(cparams, jnp.where(win.valid[..., None], win.obs, 0.0)))
            terminal_fn = make_terminal_fn(env, value_apply, cparams)
        res = cat([jax.vmap(lambda st, a, sc: jax.vmap(
            lambda s, aw: improve_fn(problem_fn(s), aw, sc, terminal_fn))(st, a))(
                w.starts, w.actions, scales[sl]) for w, (_, problem_fn, sl) in zip(wins, parts)])
        finite = jnp.all(jnp.isfinite(res.actions), axis=-1)
        weights = res.accepted[..., None] & win.valid & finite
        batch = Batch(win.obs, res.actions, weights.astype(jnp.float32), res,
                      jnp.sum(win.rewards, axis=(1, 2)), vloss, vloss0, vmean)
        return batch, cparams, copt

    return jax.jit(sample_improve)


class Compiled(NamedTuple):
    """The jitted pieces of a trainer for one (env, config): built once per process."""

    policy: Network
    optimizer: optax.GradientTransformation
    sample_improve: Callable
    regress: Callable
    evaluate: Callable
    critic: Network
    """The value network (initialised even when ``critic=False``: ``PODSState``'s fields)."""
    critic_optimizer: optax.GradientTransformation


def compile_parts(env, c, improve_fn: Callable, **sample_kw) -> Compiled:
    """The ``Compiled`` of a PODS-family config ``c`` (``PODSConfig`` or ``HDSConfig``) with the
    window step ``improve_fn``."""
    W, H = c.lengths(env)
    policy = make_policy(env.observation_size, env.action_size, c.hidden, c.activation)
    optimizer = make_optimizer(c.learning_rate, c.regression_max_grad_norm)
    critic, critic_optimizer, critic_update = make_critic(env, c)
    sample_improve = make_sample_improve(env, policy.apply, W, H, c.batch_size, improve_fn,
                                         value_apply=critic.apply, critic_update=critic_update,
                                         **sample_kw)
    return Compiled(policy, optimizer, sample_improve,
                    make_regress(policy.apply, optimizer, c.regression_steps),
                    make_evaluator(env, policy.apply, c.eval_episodes, c.eval_length),
                    critic, critic_optimizer)


def init_state(compiled: Compiled, rng) -> tuple[Any, Any, jax.Array, jax.Array, Any, Any]:
    """``(params, opt_state, run_key, eval_key, critic_params, critic_opt_state)`` of a fresh
    run from the seed ``rng``."""
    k_init, k_eval, k_run = jax.random.split(raw_key(rng), 3)
    params = compiled.policy.init(k_init)
    # fold_in: the critic's key leaves the policy's (and every run's) draws as they were
    cparams = compiled.critic.init(jax.random.fold_in(k_init, 1))
    return (params, compiled.optimizer.init(params), k_run, k_eval, cparams,
            compiled.critic_optimizer.init(cparams))


def epoch_update(compiled: Compiled, mesh, params, opt_state, key, sigma=0.0, scales=None,
                 batch_size: int | None = None, critic_params=None, critic_opt_state=None):
    """Steps 1-3 of one epoch (the critic's fit included): ``(params, opt_state, batch, loss,
    policy_grad_norm, loss_before, critic_params, critic_opt_state)``."""
    keys = shard_batch(jax.random.split(key, batch_size), mesh)
    scales = shard_batch(jnp.ones((batch_size,), jnp.float32) if scales is None
                         else jnp.asarray(scales, jnp.float32), mesh)
    params, opt_state, critic_params, critic_opt_state = replicate(
        (params, opt_state, critic_params, critic_opt_state), mesh)
    batch, critic_params, critic_opt_state = compiled.sample_improve(
        params, keys, jnp.float32(sigma), scales, critic_params, critic_opt_state)
    params, opt_state, loss, pgn, loss0 = compiled.regress(params, opt_state, batch.obs,
                                                           batch.targets, batch.weights)
    return params, opt_state, batch, loss, pgn, loss0, critic_params, critic_opt_state
