"""PODS: Policy Optimization via Differentiable Simulation (Mora et al., ICML 2021), first and
second order.

Every epoch (PODS Sec. 4, Algorithm 1):

1. **sample** ``batch_size`` start states with ``env.reset`` and roll out the deterministic MLP
   policy (tanh actions) for ``rollout_length`` steps, vmapped over the batch and sharded over
   ``jax.devices()`` (``twinrl.physics.parallel.shard_batch``);
2. **improve** each rollout's action sequence with ``twinrl.learn.trajopt.improve``: the gradient
   of the return through the simulator (Sec. 4.1, ``order=1``) or the damped Gauss–Newton step
   (Sec. 4.2, ``order=2``, the ``pods2`` algorithm), kept only if the line search finds a return
   strictly higher than the policy's own;
3. **regress** the policy onto the improved actions at the states the policy visited, with
   ``regression_steps`` full-batch Adam steps on the squared error (Sec. 4, "policy update").

With ``critic=True`` a value function is fitted between steps 1 and 2 and bootstraps each
window's return (below).

**Horizon.** The episodes are 250 steps, but the gradient of a return through a long rollout of a
chaotic system explodes (the Hybrid Differentiable Simulation study saw norms blow up past ~50
steps), and a Gauss–Newton system over all 250 actions is a 250 m x 250 m solve whose Jacobian
needs 250 m tangents through 250 steps. So the policy's rollout is cut into ``rollout_length //
horizon`` consecutive **windows** of ``horizon`` steps, each improved on its own as an open-loop
problem *from the state the policy reached at its start* (the windows are independent, so all
``batch_size * windows`` problems run in one vmapped call). Every state the policy visited gets a
target, the gradient never crosses more than ``horizon`` steps (a truncation window), and the cost
is linear in the episode length. The price is myopia: a window's objective ends at its last step
(no terminal value), which the pendulum tolerates because raising the pole pays within a second.

Gradients are further clipped (``max_grad_norm``) and a non-finite gradient or direction takes
no step (``trajopt.improve``'s guard, counted as ``nonfinite``); the regression's own update goes
through ``twinrl.physics.gradients.hygiene`` (NaN guard first, then global-norm clipping), so no
non-finite value can reach the parameters (a zeroed update is counted as ``skipped``).

**Critic (optional, ``critic=True``).** Cartpole's swing-up does not tolerate the myopia: its
open-loop window problems have poor local optima (measured on ``cartpole_swingup``: gradient
ascent with the line search on the whole 250-step episode stalls at a return of 62, Adam on it at
91, receding 50-step windows at 94, against 185-190 for the trained policies below), and the
policies regressed onto them stall below 120 (PODS 85.6 after 30 epochs, HDS 117.2 after 300).
As in SHAC (Xu et al., ICLR 2022, Sec. 3.2-3.3) a state value ``V(obs)`` of the
policy, fitted every epoch to TD(lambda) targets of that epoch's rollouts (truncated at the
rollout's end, where ``V`` bootstraps), closes each window: the window objective becomes
``sum_t gamma^t r_t + gamma^H V(s_H)`` (``trajopt``'s discount and ``terminal_fn``), so a
window's improvement is judged by where it leaves the system for the rest of the episode. The
critic is fitted *before* the windows are improved (on the rollouts just sampled), so the
terminal value has already seen the current policy's returns. Per epoch this adds
``critic_steps`` full-batch Adam steps and no simulation. For the second order the critic enters
the Gauss–Newton model linearly (``TrajoptConfig.terminal_curvature``).

**Counting ``env_steps``.** Every control step simulated for training counts once: the policy's
rollouts (``batch_size * rollout_length``), and per window and trajopt iteration the
differentiated re-simulation (``horizon``: the forward pass that carries the tangents or
cotangents; its backward pass is not counted again) plus each line-search candidate
(``line_search_steps * horizon``). The evaluation episodes behind ``return`` train nothing and
are not counted (SHAC and Brax do the same).

The trainer follows ``twinrl.learn.common``'s contract (resumable, deterministic given the seed).
``twinrl.learn.hds`` builds on this module's pieces.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from twinrl.learn import trajopt
from twinrl.learn.common import (CheckpointFn, ProgressFn, RestoreFn, compile_key, make_evaluator,
                                 raw_key)
from twinrl.learn.networks import Network, make_policy, make_value
from twinrl.learn.shac import td_lambda_targets
from twinrl.physics.gradients import global_norm, guard_stats, hygiene
from twinrl.learn.trainer import check_batch, replicate, resume, run_epochs
from twinrl.physics.parallel import batch_mesh, shard_batch

__all__ = ["PODSConfig", "PODSState", "train", "Windows", "rollout_windows",
           "regression_loss", "critic_targets"]


@dataclasses.dataclass(frozen=True)
class PODSConfig:
    """PODS hyper-parameters (defaults tuned on ``pendulum_swingup``; ``learn.tuned`` per task)."""

    epochs: int = 40
    """Number of epochs (sample, improve, regress); pendulum_swingup levels off at ~140-150 by
    epoch 20-30."""
    batch_size: int = 16
    """Start states (policy rollouts) per epoch; a multiple of ``len(jax.devices())``."""
    rollout_length: int | None = None
    """Steps of each policy rollout (None: the env's ``episode_length``)."""
    horizon: int = 50
    """Steps of each trajopt window; the rollout is cut into ``rollout_length // horizon`` windows
    (module docstring: the gradient explodes past ~50 steps)."""
    order: int = 1
    """1: first-order PODS (gradient ascent on the actions); 2: Gauss–Newton (``pods2``)."""
    step_size: float = 1.0
    """Largest step the trajopt line search tries (``TrajoptConfig.step_size``): action units per
    unit of (clipped) gradient for order 1, the fraction of the Gauss–Newton step for order 2."""
    line_search_steps: int = 8
    """Step sizes ``step_size * 2^-k``, k < this, tried per window (each one re-simulation)."""
    regularization: float = 1e-2
    """Levenberg–Marquardt damping of the Gauss–Newton matrix (order 2 only)."""
    max_grad_norm: float | None = 10.0
    """Global-norm clip of each window's ``dV/da`` before the step (None: no clipping)."""
    max_step_norm: float | None = None
    """Global-norm clip of each window's step direction after the Gauss–Newton solve, a trust
    region (``TrajoptConfig.max_step_norm``; None: none). Matters for order 2 only: order 1's
    direction is the clipped gradient."""
    iterations: int = 1
    """Trajopt improvement steps per window per epoch (``trajopt.optimize``)."""
    learning_rate: float = 3e-3
    """Adam learning rate of the regression."""
    regression_steps: int = 64
    """Full-batch Adam steps of the policy regression per epoch."""
    regression_max_grad_norm: float | None = 1.0
    """Global-norm clip of the regression gradient (after the NaN guard; None: no clipping)."""
    hidden: tuple[int, ...] = (64, 64)
    """Policy MLP hidden layer widths."""
    activation: str = "tanh"
    """Policy hidden activation (``networks.ACTIVATIONS``)."""
    critic: bool = False
    """Fit a state value ``V(obs)`` of the policy every epoch and add ``gamma^H V(s_H)`` to every
    window's (then discounted) return (module docstring, "Critic"); False: PODS's plain window
    return."""
    gamma: float = 0.99
    """Discount of the window return and of the critic's targets (``critic=True`` only; without
    a critic the window return is undiscounted)."""
    lam: float = 0.95
    """lambda of the critic's TD(lambda) targets (``critic=True`` only)."""
    critic_hidden: tuple[int, ...] = (64, 64)
    """Critic MLP hidden widths (ELU, LayerNorm after each, as SHAC's)."""
    critic_learning_rate: float = 1e-3
    """Adam learning rate of the critic."""
    critic_steps: int = 64
    """Full-batch Adam steps of the critic per epoch, on all of the epoch's rollout states."""
    eval_episodes: int = 8
    """Deterministic full episodes behind each epoch's ``return`` (same start states every epoch;
    not counted in ``env_steps``)."""
    eval_length: int | None = None
    """Steps of each evaluation episode (None: the env's ``episode_length``)."""

    def __post_init__(self):
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        object.__setattr__(self, "critic_hidden", tuple(int(h) for h in self.critic_hidden))
        for name in ("epochs", "batch_size", "horizon", "line_search_steps", "iterations",
                     "regression_steps", "eval_episodes", "critic_steps"):
            v = getattr(self, name)
            if int(v) != v or int(v) < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        for name in ("rollout_length", "eval_length"):
            v = getattr(self, name)
            if v is not None and (int(v) != v or int(v) < 1):
                raise ValueError(f"{name} must be an integer >= 1 or None, got {v!r}")
        if self.rollout_length is not None and self.horizon > self.rollout_length:
            raise ValueError(f"horizon ({self.horizon}) must be <= rollout_length "
                             f"({self.rollout_length})")
        if not 0.0 < self.gamma < 1.0:
            raise ValueError(f"gamma must be in (0, 1) (the critic's value of a truncated "
                             f"episode needs a discount), got {self.gamma}")
        if not 0.0 <= self.lam <= 1.0:
            raise ValueError(f"lam must be in [0, 1], got {self.lam}")
        for name in ("learning_rate", "step_size", "critic_learning_rate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("max_grad_norm", "max_step_norm", "regression_max_grad_norm"):
            v = getattr(self, name)
            if v is not None and not v > 0:
                raise ValueError(f"{name} must be > 0 or None, got {v}")
        # the trajopt fields are validated where they live
        self.trajopt_config()

    def trajopt_config(self) -> trajopt.TrajoptConfig:
        """The ``TrajoptConfig`` of the improvement step."""
        return trajopt.TrajoptConfig(order=self.order, step_size=self.step_size,
                                     line_search_steps=self.line_search_steps,
                                     regularization=self.regularization,
                                     max_grad_norm=self.max_grad_norm,
                                     max_step_norm=self.max_step_norm,
                                     discount=self.gamma if self.critic else 1.0)

    def lengths(self, env) -> tuple[int, int]:
        """``(windows, horizon)`` of a policy rollout in ``env``."""
        T = int(self.rollout_length or env.episode_length)
        if self.horizon > T:
            raise ValueError(f"horizon ({self.horizon}) must be <= the rollout length ({T})")
        return T // self.horizon, int(self.horizon)

    def steps_per_epoch(self, env) -> int:
        """Simulated steps of one epoch (module docstring's convention)."""
        W, H = self.lengths(env)
        per_window = self.iterations * H * (1 + self.line_search_steps)
        return self.batch_size * W * (H + per_window)


class PODSState(NamedTuple):
    """Everything a PODS run carries between epochs (a pytree of arrays of fixed structure)."""

    params: Any
    """Policy params."""
    opt_state: Any
    """Regression optimiser state (NaN-guard counters, clip state, Adam moments)."""
    rng: jax.Array
    """uint32[2] key: the source of every later random draw."""
    eval_key: jax.Array
    """uint32[2] key of the evaluation episodes (fixed, so every epoch meets the same starts)."""
    epoch: jax.Array
    """int32: completed epochs."""
    env_steps: jax.Array
    """int64 (NumPy): simulated steps so far."""
    critic_params: Any = None
    """Critic params (initialised, and carried unchanged, when ``critic=False`` too, so the
    state's structure does not depend on the config)."""
    critic_opt_state: Any = None
    """Critic optimiser state."""


# --------------------------------------------------------------------------- pieces
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


def regression_loss(apply_fn, params, obs, targets, weights):
    """Weighted mean squared error ``sum w |pi(o) - a*|^2 / sum w`` (PODS Sec. 4 policy update)."""
    pred = apply_fn(params, obs)
    se = jnp.sum(jnp.square(pred - targets), axis=-1)
    return jnp.sum(weights * se) / jnp.maximum(jnp.sum(weights), 1.0)


def make_optimizer(learning_rate: float, max_grad_norm: float | None):
    """NaN guard, global-norm clip, Adam: a non-finite update never reaches the parameters."""
    return optax.chain(hygiene(max_grad_norm), optax.adam(learning_rate))


def make_regress(apply_fn, optimizer, steps: int):
    """A jitted ``regress(params, opt_state, obs, targets, weights)`` of ``steps`` full-batch
    steps. Returns ``(params, opt_state, final_loss, first_grad_norm, initial_loss)`` (the loss
    before the first step says how far the targets moved; the final one how well the policy fits
    them); with no weight at all
    (nothing accepted) the params and optimiser state are returned unchanged (Adam's momentum
    would otherwise keep moving them)."""

    def regress(params, opt_state, obs, targets, weights):
        w = weights.reshape(-1).astype(jnp.float32)
        obs = obs.reshape(w.shape[0], -1)
        targets = targets.reshape(w.shape[0], -1)
        # where(), so a masked NaN cannot leak through 0 * NaN
        keep = w > 0
        obs = jnp.where(keep[:, None], obs, 0.0)
        targets = jnp.where(keep[:, None], targets, 0.0)

        def body(carry, _):
            p, s = carry
            loss, g = jax.value_and_grad(
                lambda q: regression_loss(apply_fn, q, obs, targets, w))(p)
            u, s = optimizer.update(g, s, p)
            return (optax.apply_updates(p, u), s), (loss, global_norm(g))

        (p, s), (losses, norms) = jax.lax.scan(body, (params, opt_state), None, length=steps)
        any_w = jnp.sum(w) > 0
        pick = lambda new, old: jax.tree_util.tree_map(  # noqa: E731
            lambda a, b: jnp.where(any_w, a, b), new, old)
        final = regression_loss(apply_fn, p, obs, targets, w)
        return (pick(p, params), pick(s, opt_state), jnp.where(any_w, final, 0.0), norms[0],
                jnp.where(any_w, losses[0], 0.0))

    return jax.jit(regress)


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


def critic_stats(batch, critic: bool) -> dict[str, float]:
    """The critic's per-epoch figures (none without a critic)."""
    if not critic:
        return {}
    return {"value_loss": float(batch.value_loss),
            "value_loss_before": float(batch.value_loss_before), "value": float(batch.value)}


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


# --------------------------------------------------------------------------- critic
def critic_targets(value_fn: Callable, obs, rewards, valid, final_obs, final_valid,
                   gamma: float, lam: float) -> jax.Array:
    """TD(lambda) targets (B, T) of the value of each visited state (SHAC Sec. 3.3, Eq. 5;
    ``twinrl.learn.shac.td_lambda_targets``) from rollouts (B, T) of the policy.

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


def make_terminal_fn(env, value_apply: Callable, cparams) -> trajopt.TerminalFn:
    """``s_T -> V(observe(s_T))`` on ``trajopt``'s state vector ``concat(qpos, qvel)``."""
    nq = env.sim.nq
    return lambda s: value_apply(cparams, env.observe(s[:nq], s[nq:]))


# --------------------------------------------------------------------------- train
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


def make_critic(env, c: PODSConfig
                ) -> tuple[Network, optax.GradientTransformation, Callable | None]:
    """``(critic, critic_optimizer, critic_update or None)`` of the config."""
    critic = make_value(env.observation_size, c.critic_hidden, "elu", layer_norm=True)
    optimizer = make_optimizer(c.critic_learning_rate, None)
    update = (make_critic_update(critic.apply, optimizer, c.critic_steps, c.gamma, c.lam)
              if c.critic else None)
    return critic, optimizer, update


def compile_parts(env, c: PODSConfig, improve_fn: Callable, **sample_kw) -> Compiled:
    """The ``Compiled`` of a PODS-family config with the window step ``improve_fn``."""
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


@functools.lru_cache(maxsize=16)
def _build(env, key: PODSConfig, devices: tuple) -> Compiled:
    # Memoised because compiling a gradient through MJX takes minutes on a CPU: a second run with
    # the same env and config (a resumed run, a test of determinism) must not trace it again.
    # The cache holds only pure functions of immutable inputs.
    del devices
    c = key
    tcfg = c.trajopt_config()
    return compile_parts(env, c, lambda problem, a, scale, terminal_fn: improve_window(
        problem, a, tcfg, c.iterations, terminal_fn))


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


def train(env, config: PODSConfig = PODSConfig(), rng: jax.Array | int | None = None, *,
          progress_fn: ProgressFn | None = None, checkpoint_fn: CheckpointFn | None = None,
          restore: RestoreFn | None = None) -> tuple[Network, Any, dict[str, list[float]]]:
    """Train a deterministic policy on ``env`` with PODS; the contract of ``twinrl.learn.common``.

    Metrics per epoch: ``epoch`` (completed), ``env_steps`` (cumulative, module docstring),
    ``wall_s``, ``return`` (mean deterministic evaluation return), ``return_std``, ``grad_norm``
    (mean ``|dV/da|`` of the windows' first improvement step, before clipping, over finite ones),
    ``accepted_frac`` (windows whose line search improved on the policy), ``improvement`` (mean
    return gain per window), ``alpha`` (mean accepted step), ``nonfinite`` (windows whose gradient
    or step was non-finite this epoch: no step taken), ``rollout_return`` (mean training-rollout
    return), ``loss`` (regression loss after the epoch's steps), ``policy_grad_norm`` (regression
    gradient norm at the first step), ``loss_before`` (regression loss before its first step:
    how far the targets are from the policy) and ``skipped`` (regression updates zeroed by the
    NaN guard, cumulative); with ``critic=True`` also ``value_loss`` / ``value_loss_before`` (the
    critic's squared TD(lambda) error after / before its fit) and ``value`` (mean critic value of
    the visited states).
    """
    if type(config) is not PODSConfig:
        raise TypeError(f"config must be a PODSConfig (an HDSConfig goes to twinrl.learn.hds."
                        f"train), got {type(config).__name__}")
    c = config
    check_batch(c.batch_size)
    compiled = _build(env, compile_key(c), tuple(jax.devices()))
    mesh = batch_mesh()
    params, opt_state, k_run, k_eval, cparams, copt = init_state(compiled, rng)
    state = PODSState(params=params, opt_state=opt_state, rng=k_run, eval_key=k_eval,
                      epoch=jnp.zeros((), jnp.int32), env_steps=np.zeros((), np.int64),
                      critic_params=cparams, critic_opt_state=copt)
    state, log, done = resume(restore, state, PODSState)
    steps_per_epoch = c.steps_per_epoch(env)

    def epoch(e, state):
        rng_next, k_batch = jax.random.split(state.rng)
        params, opt_state, batch, loss, pgn, loss0, cparams, copt = epoch_update(
            compiled, mesh, state.params, state.opt_state, k_batch, batch_size=c.batch_size,
            critic_params=state.critic_params, critic_opt_state=state.critic_opt_state)
        env_steps = np.asarray(int(state.env_steps) + steps_per_epoch, np.int64)
        state = PODSState(params=params, opt_state=opt_state, rng=rng_next,
                          eval_key=state.eval_key, epoch=state.epoch + 1, env_steps=env_steps,
                          critic_params=cparams, critic_opt_state=copt)
        returns = np.asarray(compiled.evaluate(params, state.eval_key))
        return state, dict(env_steps=env_steps, **{"return": returns.mean()},
                           return_std=returns.std(), **window_stats(batch.result),
                           rollout_return=np.asarray(batch.rollout_return).mean(), loss=loss,
                           loss_before=loss0, policy_grad_norm=pgn,
                           skipped=guard_stats(opt_state)["grad/skipped"],
                           **critic_stats(batch, c.critic))

    state = run_epochs(state, log, done, c.epochs, epoch, progress_fn=progress_fn,
                       checkpoint_fn=checkpoint_fn)
    return compiled.policy, state.params, log.as_dict()
