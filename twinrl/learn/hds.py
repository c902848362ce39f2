"""HDS: the Hybrid Differentiable Simulation study's trainer, PODS with exploration, a
simulated-annealing step size and rollouts through a (learned) dynamics model.

HDS is ``twinrl.learn.pods`` (sample, improve each window of the rollout with the gradient of its
return, regress the policy onto the accepted improvements; PODS Sec. 4) with three changes the
HDS study made:

- **exploration noise**: the executed actions are ``clip(pi(s) + sigma_e * eps, -1, 1)``,
  ``eps ~ N(0, I)``, with ``sigma_e = noise_std * noise_decay ** e`` at epoch ``e``. The trajopt
  step improves the executed (noisy) sequence and accepts a candidate only if it beats that
  sequence's own return, so the policy is pulled towards improved versions of what it explored.
- **simulated-annealing step size**: the trajopt step size ``alpha`` is the state of a simulated
  annealing chain. Every epoch proposes ``alpha' = alpha * exp(anneal_proposal_std * xi)``
  (clipped to ``step_size_bounds``); half the rollouts (even indices) improve their windows with
  ``alpha``, the other half with ``alpha'``, at no extra cost. The energy of a step size is the
  mean improvement per simulated step it achieved, ``G = mean (V_new - V_old) / horizon``; the
  proposal replaces ``alpha`` if ``G' >= G`` or with probability ``exp((G' - G) / T_e)`` (the
  Metropolis rule), at a temperature ``T_e = anneal_temperature * anneal_cooling ** e`` that
  cools every epoch, so early epochs wander over step sizes and later ones settle. ``step_size``
  (the chain's value used this epoch), ``step_size_proposal``, ``temperature`` and
  ``sa_accept`` are logged every epoch.
- **hybrid rollouts**: a fraction ``model_fraction`` (beta) of the batch's rollouts, the last
  ``round(beta * batch_size)``, is simulated through ``dynamics(state, action) -> State``, a
  drop-in replacement for ``env.step`` (the learned hybrid model of ``twinrl.sim2real.hybrid``
  plugs in here): the policy's rollout, the differentiated re-simulation and the line search of
  those rollouts all go through it, with the task's reward of the predicted state. It must be
  differentiable, and its ``State.pipeline_state`` must carry ``qpos`` and ``qvel`` as
  ``env.step``'s does. The evaluation (``return``) always runs in ``env``.

The optional critic (``critic=True``: a learned value bootstrapping each window's return) is
``twinrl.learn.critic``'s, as PODS's; it is fitted on the executed (noisy) rollouts.

``env_steps`` follows ``twinrl.learn.pods`` (every simulated step, line searches and gradient
re-simulations included, evaluation excluded) and counts the steps through ``dynamics`` too;
``model_steps`` (cumulative) is the part of them that went through ``dynamics``, and
``model_rollouts`` is the number of the epoch's rollouts that did (per epoch;
``model_rollouts_total`` is cumulative).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.learn import distributed, trajopt
from twinrl.learn.common import CheckpointFn, ProgressFn, RestoreFn, compile_key
from twinrl.learn.networks import Network
from twinrl.learn.critic import critic_stats
from twinrl.learn.pods import PODSConfig
from twinrl.learn.windows import (Compiled, compile_parts, epoch_update, improve_window,
                                  init_state, window_stats)
from twinrl.learn.trainer import check_batch, resume, run_epochs
from twinrl.physics.gradients import guard_stats
from twinrl.physics.parallel import batch_mesh

__all__ = ["HDSConfig", "HDSState", "train", "improve_scaled"]


@dataclasses.dataclass(frozen=True)
class HDSConfig(PODSConfig):
    """HDS hyper-parameters: every ``PODSConfig`` field plus exploration, annealing and the model
    fraction. ``step_size`` is the annealing chain's starting step size."""

    noise_std: float = 0.3
    """``sigma_0``: standard deviation of the exploration noise added to the actions at epoch 0."""
    noise_decay: float = 0.9
    """Per-epoch factor of the noise: ``sigma_e = noise_std * noise_decay ** e``."""
    anneal_temperature: float = 0.01
    """``T_0`` of the step-size annealing, in units of return improvement per simulated step."""
    anneal_cooling: float = 0.9
    """Per-epoch cooling factor: ``T_e = anneal_temperature * anneal_cooling ** e``."""
    anneal_proposal_std: float = 0.5
    """Standard deviation of the log-step-size proposal ``log alpha' = log alpha + N(0, s^2)``."""
    step_size_bounds: tuple[float, float] = (0.05, 20.0)
    """Range the annealed step size is kept in."""
    model_fraction: float = 0.0
    """beta: fraction of each epoch's rollouts simulated through ``dynamics`` (0: none)."""

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "step_size_bounds",
                           tuple(float(b) for b in self.step_size_bounds))
        self.check_fields(non_negative=("noise_std", "anneal_proposal_std"),
                          within={"noise_decay": "(0, 1]", "anneal_cooling": "(0, 1]",
                                  "model_fraction": "[0, 1]"},
                          positive=("anneal_temperature",))
        bounds = self.step_size_bounds
        if len(bounds) != 2 or not 0 < bounds[0] <= self.step_size <= bounds[1]:
            raise ValueError(f"HDSConfig.step_size_bounds must be (low, high) with 0 < low <= "
                             f"step_size ({self.step_size}) <= high, got {bounds}")
        if self.batch_size < 2:
            raise ValueError(f"HDSConfig.batch_size must be >= 2 (half the rollouts test the "
                             f"annealing proposal), got {self.batch_size}")

    @property
    def model_rollouts(self) -> int:
        """Rollouts per epoch through ``dynamics``: ``round(model_fraction * batch_size)``."""
        return int(round(self.model_fraction * self.batch_size))




class HDSState(NamedTuple):
    """Everything an HDS run carries between epochs (a pytree of arrays of fixed structure)."""

    params: Any
    """Policy params."""
    opt_state: Any
    """Regression optimiser state."""
    rng: jax.Array
    """uint32[2] key: the source of every later random draw."""
    eval_key: jax.Array
    """uint32[2] key of the evaluation episodes."""
    epoch: jax.Array
    """int32: completed epochs."""
    env_steps: jax.Array
    """int64 (NumPy): simulated steps so far (``dynamics`` steps included)."""
    step_size: jax.Array
    """float32: the annealing chain's current step size."""
    model_rollouts: jax.Array
    """int64 (NumPy): rollouts simulated through ``dynamics`` so far."""
    model_steps: jax.Array
    """int64 (NumPy): steps simulated through ``dynamics`` so far."""
    critic_params: Any = None
    """Critic params (``PODSState.critic_params``)."""
    critic_opt_state: Any = None
    """Critic optimiser state."""


def improve_scaled(problem, actions: jax.Array, config: trajopt.TrajoptConfig,
                   step_size: jax.Array, iterations: int = 1,
                   terminal_fn: trajopt.TerminalFn | None = None) -> trajopt.TrajoptResult:
    """``iterations`` steps of ``trajopt.improve`` with a traced step size (HDS anneals it;
    ``TrajoptConfig.step_size`` is a static float): the direction is scaled by
    ``step_size / config.step_size``, so the line search tries ``step_size * 2^-k``. The same
    hygiene: a non-finite gradient, Hessian or direction takes no step and is flagged.
    ``terminal_fn`` is the critic's terminal value (``trajopt.improve``)."""
    scale = jnp.asarray(step_size, actions.dtype) / config.step_size
    return improve_window(problem, actions, config, int(iterations), terminal_fn, scale)


@functools.lru_cache(maxsize=16)
def _build(env, key: HDSConfig, dynamics: Callable | None, devices: tuple) -> Compiled:
    # Memoised like ``pods._build``: MJX gradients take minutes to compile on a CPU.
    del devices
    c = key
    tcfg = c.trajopt_config()
    return compile_parts(
        env, c, lambda problem, a, scale, terminal_fn: improve_scaled(
            problem, a, tcfg, scale, c.iterations, terminal_fn),
        dynamics=dynamics, n_model=c.model_rollouts, noisy=c.noise_std > 0)


def _energies(batch, horizon: int) -> tuple[float, float]:
    """Mean improvement per simulated step of the even (current step size) and odd (proposal)
    rollouts."""
    gain = (np.asarray(batch.result.value, np.float64)
            - np.asarray(batch.result.old_value, np.float64)) / horizon
    gain = np.where(np.isfinite(gain), gain, 0.0)
    return float(gain[0::2].mean()), float(gain[1::2].mean())


def train(env, config: HDSConfig = HDSConfig(), rng: jax.Array | int | None = None, *,
          dynamics: Callable | None = None, progress_fn: ProgressFn | None = None,
          checkpoint_fn: CheckpointFn | None = None,
          restore: RestoreFn | None = None) -> tuple[Network, Any, dict[str, list[float]]]:
    """Train a deterministic policy on ``env`` with HDS; the contract of ``twinrl.learn.common``.

    ``dynamics(state, action) -> State`` replaces ``env.step`` for the ``model_fraction`` of the
    rollouts (required when ``model_fraction > 0``). Metrics per epoch: those of ``pods.train``
    plus ``noise_scale`` (``sigma_e``), ``step_size`` (the annealed step size used this epoch),
    ``step_size_proposal``, ``temperature``, ``sa_accept`` (1 if the proposal was taken),
    ``energy`` / ``energy_proposal`` (improvement per step of each half), ``model_rollouts``
    (rollouts through ``dynamics`` this epoch), ``model_rollouts_total`` and ``model_steps``
    (cumulative).
    """
    if not isinstance(config, HDSConfig):
        raise TypeError(f"config must be an HDSConfig, got {type(config).__name__}")
    c = config
    n_model = c.model_rollouts
    if n_model > 0 and dynamics is None:
        raise ValueError(f"model_fraction={c.model_fraction} sends {n_model} of "
                         f"{c.batch_size} rollouts per epoch through `dynamics`, but dynamics is "
                         f"None: pass dynamics(state, action) -> State or set model_fraction=0")
    if dynamics is not None and not callable(dynamics):
        raise TypeError(f"dynamics must be a callable (state, action) -> State, "
                        f"got {type(dynamics).__name__}")
    check_batch(c.batch_size)
    compiled = _build(env, compile_key(c), dynamics if n_model else None, tuple(jax.devices()))
    mesh = batch_mesh()
    W, H = c.lengths(env)
    params, opt_state, k_run, k_eval, cparams, copt = init_state(compiled, rng)
    zero = np.zeros((), np.int64)
    state = HDSState(params=params, opt_state=opt_state, rng=k_run, eval_key=k_eval,
                     epoch=jnp.zeros((), jnp.int32), env_steps=zero,
                     step_size=jnp.asarray(c.step_size, jnp.float32), model_rollouts=zero,
                     model_steps=zero, critic_params=cparams, critic_opt_state=copt)
    state, log, done = resume(restore, state, HDSState)
    steps_per_epoch = c.steps_per_epoch(env)
    model_steps_per_epoch = steps_per_epoch * n_model // c.batch_size
    lo, hi = c.step_size_bounds
    log_lo, log_hi = math.log(lo), math.log(hi)

    def epoch(e, state):
        rng_next, k_batch, k_prop, k_acc = jax.random.split(state.rng, 4)
        sigma = c.noise_std * c.noise_decay ** e
        temperature = c.anneal_temperature * c.anneal_cooling ** e
        alpha = float(state.step_size)
        xi = float(jax.random.normal(k_prop))
        proposal = float(np.float32(math.exp(min(max(math.log(alpha)
                                                     + c.anneal_proposal_std * xi, log_lo),
                                                 log_hi))))
        scales = np.where(np.arange(c.batch_size) % 2 == 0, alpha, proposal).astype(np.float32)
        params, opt_state, batch, loss, pgn, loss0, cparams, copt = epoch_update(
            compiled, mesh, state.params, state.opt_state, k_batch, sigma=sigma, scales=scales,
            batch_size=c.batch_size, critic_params=state.critic_params,
            critic_opt_state=state.critic_opt_state)
        if distributed.is_distributed():  # the energies and figures read every process's windows
            batch = distributed.to_host(batch)
        energy, energy_prop = _energies(batch, H)
        u = float(jax.random.uniform(k_acc))
        take = energy_prop >= energy or u < math.exp((energy_prop - energy) / temperature)
        state = HDSState(
            params=params, opt_state=opt_state, rng=rng_next, eval_key=state.eval_key,
            epoch=state.epoch + 1,
            env_steps=np.asarray(int(state.env_steps) + steps_per_epoch, np.int64),
            step_size=jnp.asarray(proposal if take else alpha, jnp.float32),
            model_rollouts=np.asarray(int(state.model_rollouts) + n_model, np.int64),
            model_steps=np.asarray(int(state.model_steps) + model_steps_per_epoch, np.int64),
            critic_params=cparams, critic_opt_state=copt)
        returns = np.asarray(compiled.evaluate(params, state.eval_key))
        return state, dict(env_steps=state.env_steps, **{"return": returns.mean()},
                           return_std=returns.std(), **window_stats(batch.result),
                           rollout_return=np.asarray(batch.rollout_return).mean(), loss=loss,
                           loss_before=loss0, policy_grad_norm=pgn,
                           skipped=guard_stats(opt_state)["grad/skipped"],
                           **critic_stats(batch, c.critic),
                           noise_scale=sigma, step_size=alpha, step_size_proposal=proposal,
                           temperature=temperature, sa_accept=float(take), energy=energy,
                           energy_proposal=energy_prop, model_rollouts=n_model,
                           model_rollouts_total=state.model_rollouts,
                           model_steps=state.model_steps)

    state = run_epochs(state, log, done, c.epochs, epoch, progress_fn=progress_fn,
                       checkpoint_fn=checkpoint_fn)
    return compiled.policy, state.params, log.as_dict()
