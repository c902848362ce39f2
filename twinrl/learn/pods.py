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
Its epoch (sampling, window improvement, regression) is ``twinrl.learn.windows``, shared with
``twinrl.learn.hds``; the critic is ``twinrl.learn.critic``'s TD(lambda) critic.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.learn import distributed, trajopt
from twinrl.learn.common import (CheckpointFn, JSONConfig, ProgressFn, RestoreFn, compile_key,
                                 regression_loss)
from twinrl.learn.critic import critic_stats, critic_targets
from twinrl.learn.networks import ACTIVATIONS, Network
from twinrl.learn.trainer import check_batch, resume, run_epochs
from twinrl.learn.windows import (Compiled, Windows, compile_parts, epoch_update, improve_window,
                                  init_state, rollout_windows, window_stats)
from twinrl.physics.gradients import guard_stats
from twinrl.physics.parallel import batch_mesh

# Windows, rollout_windows, regression_loss and critic_targets are PODS's pieces, kept importable
# from here; they live in the kit (``windows``, ``common``, ``critic``) that HDS shares.
__all__ = ["PODSConfig", "PODSState", "train", "Windows", "rollout_windows",
           "regression_loss", "critic_targets"]


@dataclasses.dataclass(frozen=True)
class PODSConfig(JSONConfig):
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
        self.check_fields(
            widths=("hidden", "critic_hidden"), choices={"activation": ACTIVATIONS},
            at_least_one=("epochs", "batch_size", "horizon", "line_search_steps", "iterations",
                          "regression_steps", "eval_episodes", "critic_steps", "rollout_length",
                          "eval_length"),
            # gamma < 1: the critic's value of a truncated episode needs a discount
            within={"gamma": "(0, 1)", "lam": "[0, 1]"},
            positive=("learning_rate", "step_size", "critic_learning_rate", "max_grad_norm",
                      "max_step_norm", "regression_max_grad_norm"),
            optional=("rollout_length", "eval_length", "max_grad_norm", "max_step_norm",
                      "regression_max_grad_norm"))
        if self.rollout_length is not None and self.horizon > self.rollout_length:
            raise ValueError(f"{type(self).__name__}.horizon ({self.horizon}) must be <= "
                             f"rollout_length ({self.rollout_length})")
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
        if distributed.is_distributed():  # the figures below read every process's windows
            batch = distributed.to_host(batch)
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
