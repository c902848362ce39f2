"""SHAC: Short-Horizon Actor-Critic through the differentiable simulator.

Xu et al., "Accelerated Policy Learning with Parallel Differentiable Simulation", ICLR 2022.
``N`` environments run in parallel (vmapped, the batch sharded over ``jax.devices()``); every epoch
each rolls the stochastic policy forward ``h`` steps and the actor is improved by
backpropagation through time *through the simulator* over that short window only (Sec. 3.2:
long horizons give exploding, noisy gradients, and short ones bias the return, which the critic
repairs). Per epoch (Algorithm 1):

1. **Actor** (Sec. 3.2, Eq. 2): minimise
   ``L = -1/(N h) sum_envs sum_segments [ sum_{t in segment} gamma^(t - t0) r_t
   + gamma^(t1 - t0) V_target(s_t1) ]``, where a segment runs from the window's start (or an
   episode's reset) to its end (or the episode's end). ``V_target(s_t1)`` is 0 when the episode
   ended by the simulation diverging (a termination) and the target critic's value of the final
   state when it ended by the time limit (a truncation: the task goes on). The gradient flows
   through actions, states and the terminal value; the state carried into the next window has
   its gradient stopped, and environments that finished an episode restart from ``env.reset``.
2. **Critic** (Sec. 3.3, Eq. 4-5): regress ``V`` on TD(lambda) targets computed on the window's
   states with the target critic's values (``td_lambda_targets``), for ``critic_iterations``
   passes of ``critic_minibatches`` shuffled minibatches.
3. **Target critic**: Polyak averaging ``V_target <- alpha V_target + (1 - alpha) V``
   (``target_alpha``, SHAC's 0.2).

Policy: as in SHAC (Appendix A.3), a diagonal Gaussian whose mean is an MLP and whose
state-independent log standard deviation is learned, squashed by tanh:
``a = tanh(mu(s) + exp(log_std) * eps)``, ``eps ~ N(0, I)``. The sample is *reparameterised*, so
the BPTT gradient reaches ``mu`` and ``log_std`` through the sampled action, and exploration
shrinks as the actor learns it need not explore (no separate noise schedule to tune, unlike a
deterministic policy plus hand-set noise). The deterministic evaluation policy is the mode,
``tanh(mu(s))``: the returned ``policy`` is exactly that MLP (tanh output), so
``policy.apply(params, obs)`` is a plain obs -> action in [-1, 1] and a checkpoint needs only its
params and ``policy.config``.

Gradient hygiene (``twinrl.physics.gradients``): both optimisers are
``chain(nan_guard, clip_by_global_norm, adam)``: an update holding a NaN/inf is zeroed and
counted (metrics ``skipped`` and ``critic_skipped``) before it reaches the norm, Adam's moments or
the parameters.

Follows the resumable contract of ``twinrl.learn.common``: every random draw comes from the key in
the train state (``SHACState``), so ``restore`` continues a killed run exactly.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from twinrl.learn import distributed
from twinrl.learn.common import (CheckpointFn, JSONConfig, ProgressFn, RestoreFn, make_evaluator,
                                 raw_key)
from twinrl.learn.critic import td_lambda_targets
from twinrl.learn.networks import ACTIVATIONS, Network, fold_normaliser
from twinrl.learn.shac_epoch import (Parts, SHACState, actor_loss, critic_update, deployed,
                                     epoch_step, init_state, make_networks, make_parts)
from twinrl.learn.trainer import check_batch, jit_sharded_epoch, resume, run_epochs
from twinrl.physics.parallel import batch_mesh

__all__ = ["SHACConfig", "SHACState", "train", "td_lambda_targets", "make_networks", "Parts",
           "make_parts", "init_state", "actor_loss", "critic_update", "epoch_step", "deployed",
           "fold_normaliser"]


@dataclasses.dataclass(frozen=True)
class SHACConfig(JSONConfig):
    """Hyper-parameters of SHAC (defaults: SHAC's cartpole settings, Appendix A.4, except the
    learning rates, 2e-3 for both, which ``pendulum_swingup`` is solved with;
    ``twinrl.learn.tuned`` sets SHAC's actor 1e-2 / critic 1e-3 for ``cartpole_swingup``)."""

    epochs: int = 300
    """Number of epochs; each is one actor update on ``num_envs * horizon`` simulated steps."""
    num_envs: int = 64
    """N, environments simulated in parallel (a multiple of ``len(jax.devices())``)."""
    horizon: int = 32
    """h, the short horizon: steps of backpropagation through the simulator per actor update."""
    gamma: float = 0.99
    """Discount factor."""
    lam: float = 0.95
    """lambda of the critic's TD(lambda) targets."""
    actor_lr: float = 2e-3
    """Actor Adam learning rate (decayed linearly to ``lr_end`` over ``epochs`` if
    ``lr_schedule == "linear"``)."""
    critic_lr: float = 2e-3
    """Critic Adam learning rate (same schedule)."""
    lr_schedule: str = "linear"
    """``"linear"`` (SHAC's decay to ``lr_end``) or ``"constant"``."""
    lr_end: float = 1e-5
    """Learning rate at the last epoch of the linear schedule."""
    adam_b1: float = 0.7
    """Adam beta1 (SHAC uses (0.7, 0.95): short memory, the gradients change with the policy)."""
    adam_b2: float = 0.95
    """Adam beta2."""
    max_grad_norm: float = 1.0
    """Global-norm clip of the actor's and the critic's gradients."""
    critic_iterations: int = 16
    """Passes over the window's (state, target) pairs per epoch."""
    critic_minibatches: int = 4
    """Minibatches per pass; ``num_envs * horizon`` must be divisible by it."""
    target_alpha: float = 0.2
    """Polyak weight of the *old* target critic: ``V_target <- alpha V_target + (1 - alpha) V``."""
    init_log_std: float = -1.0
    """Initial log standard deviation of the Gaussian policy (before tanh)."""
    actor_hidden: tuple[int, ...] = (64, 64)
    """Hidden widths of the policy mean MLP."""
    actor_activation: str = "elu"
    """Hidden activation of the policy (see ``twinrl.learn.networks.ACTIVATIONS``)."""
    critic_hidden: tuple[int, ...] = (64, 64)
    """Hidden widths of the critic MLP (LayerNorm after each, as in SHAC)."""
    critic_activation: str = "elu"
    """Hidden activation of the critic."""
    normalize_observations: bool = True
    """Standardise observations with running mean/std (SHAC's ``obs_rms``) before the actor and
    the critic; the returned policy has the standardisation folded into its first layer."""
    eval_episodes: int = 8
    """Full deterministic episodes behind each epoch's ``return`` metric (not counted in
    ``env_steps``: they train nothing)."""
    episode_length: int | None = None
    """Steps per episode (time limit of training and evaluation); default ``env.episode_length``."""

    def __post_init__(self):
        self.check_fields(
            widths=("actor_hidden", "critic_hidden"), optional=("episode_length",),
            at_least_one=("epochs", "num_envs", "horizon", "critic_iterations",
                          "critic_minibatches", "eval_episodes", "episode_length"),
            within={"gamma": "[0, 1]", "lam": "[0, 1]", "target_alpha": "[0, 1]"},
            positive=("actor_lr", "critic_lr", "max_grad_norm"),
            choices={"lr_schedule": ("linear", "constant"), "actor_activation": ACTIVATIONS,
                     "critic_activation": ACTIVATIONS})
        if (self.num_envs * self.horizon) % self.critic_minibatches:
            raise ValueError(f"SHACConfig: num_envs * horizon = {self.num_envs * self.horizon} "
                             f"must be divisible by critic_minibatches = "
                             f"{self.critic_minibatches}")


def train(env, config: SHACConfig = SHACConfig(), rng: jax.Array | None = None, *,
          progress_fn: ProgressFn | None = None, checkpoint_fn: CheckpointFn | None = None,
          restore: RestoreFn | None = None) -> tuple[Network, Any, dict[str, list[float]]]:
    """Train a policy on ``env`` with SHAC; the contract of ``twinrl.learn.common``.

    Returns ``(policy, params, metrics)``: ``policy.apply(params, obs)`` is the deterministic
    action ``tanh(mu(obs))`` in [-1, 1]. Metrics per epoch: ``epoch``, ``env_steps`` (``epoch *
    num_envs * horizon``), ``wall_s``, ``return`` (deterministic evaluation), ``grad_norm`` (actor
    gradient before clipping), ``actor_loss``, ``critic_loss``, ``train_reward`` (mean per-step
    reward of the stochastic policy in the window), ``std`` (mean policy standard deviation),
    ``skipped`` / ``critic_skipped`` (cumulative updates dropped by the NaN guard).
    """
    c = config
    rng = jax.random.PRNGKey(0) if rng is None else raw_key(rng)
    N, h = int(c.num_envs), int(c.horizon)
    check_batch(N, "num_envs")
    mesh = batch_mesh()
    p = make_parts(env, c)
    state, log, done = resume(restore, init_state(p, rng), SHACState)
    # Environments split over the devices, everything else replicated, in and out of the epoch.
    # several processes: the actor's gradient summed once an epoch (epoch_step's ``mesh``)
    per_device = mesh if distributed.is_distributed() else None
    state, epoch_fn = jit_sharded_epoch(lambda s: epoch_step(p, s, per_device), state, mesh,
                                        ("env_state", "ep_step"), 3)
    evaluate = make_evaluator(env, p.policy.apply, c.eval_episodes, p.episode_length)

    def epoch(e, state):
        state, m, k_eval = epoch_fn(state)
        ret = jnp.mean(evaluate(deployed(state), k_eval))
        return state, dict(env_steps=(e + 1) * N * h, **{"return": ret}, **m)

    state = run_epochs(state, log, done, c.epochs, epoch, progress_fn=progress_fn,
                       checkpoint_fn=checkpoint_fn)
    return p.policy, deployed(state), log.as_dict()
