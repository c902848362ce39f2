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
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax

from twinrl.learn.common import (CheckpointFn, JSONConfig, ProgressFn, RestoreFn, make_evaluator,
                                 raw_key, tree_where)
from twinrl.learn.critic import minibatch_fit, td_lambda_targets
from twinrl.learn.networks import (Network, NetworkConfig, fold_normaliser, init_obs_stats,
                                   make_network, make_value, obs_std, update_obs_stats)
from twinrl.learn.trainer import jit_sharded_epoch, resume, run_epochs
from twinrl.physics.gradients import clip_by_global_norm, global_norm, guard_stats, nan_guard
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
        object.__setattr__(self, "actor_hidden", tuple(int(x) for x in self.actor_hidden))
        object.__setattr__(self, "critic_hidden", tuple(int(x) for x in self.critic_hidden))
        for name in ("epochs", "num_envs", "horizon", "critic_iterations", "critic_minibatches",
                     "eval_episodes"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"SHACConfig.{name} must be >= 1, got {getattr(self, name)}")
        if (self.num_envs * self.horizon) % self.critic_minibatches:
            raise ValueError(f"num_envs * horizon = {self.num_envs * self.horizon} must be "
                             f"divisible by critic_minibatches = {self.critic_minibatches}")
        for name in ("gamma", "lam", "target_alpha"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"SHACConfig.{name} must be in [0, 1], got {getattr(self, name)}")
        for name in ("actor_lr", "critic_lr", "max_grad_norm"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SHACConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.lr_schedule not in ("linear", "constant"):
            raise ValueError(f"lr_schedule must be 'linear' or 'constant', got "
                             f"{self.lr_schedule!r}")
        if self.episode_length is not None and int(self.episode_length) < 1:
            raise ValueError(f"episode_length must be >= 1 or None, got {self.episode_length}")


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


def make_networks(obs_size: int, action_size: int, config: SHACConfig
                  ) -> tuple[Network, Network, Network]:
    """``(policy, policy_pre_tanh, critic)``: the deterministic policy (tanh output, the one
    ``train`` returns), the same MLP without the tanh (the Gaussian's mean), and the critic."""
    pcfg = NetworkConfig(hidden=config.actor_hidden, activation=config.actor_activation,
                         output="tanh")
    policy = make_network(obs_size, action_size, pcfg)
    pre = make_network(obs_size, action_size, dataclasses.replace(pcfg, output="linear"))
    critic = make_value(obs_size, config.critic_hidden, config.critic_activation, layer_norm=True)
    return policy, pre, critic


def _optimizer(lr: float, config: SHACConfig, updates: int) -> optax.GradientTransformation:
    if config.lr_schedule == "linear":
        lr = optax.linear_schedule(lr, config.lr_end, max(int(updates), 1))
    return optax.chain(nan_guard(), clip_by_global_norm(config.max_grad_norm),
                       optax.adam(lr, b1=config.adam_b1, b2=config.adam_b2))


class Parts(NamedTuple):
    """What SHAC's pieces share for one (env, config): networks, optimisers, the vmapped env."""

    config: SHACConfig
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


def make_parts(env, c: SHACConfig) -> Parts:
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


def actor_loss(p: Parts, actor, target_critic, env_state, ep_step, obs_norm, key):
    """SHAC's short-horizon actor loss (Eq. 2) and the window's data for the critic:
    ``(loss, (next env_state, next ep_step, obs, rewards, next values, boundaries))``."""
    c, N, h, T = p.config, int(p.config.num_envs), int(p.config.horizon), p.episode_length
    k_noise, k_reset = jax.random.split(key)
    # One fresh state per environment serves any episode that ends inside this window
    # (h <= T, so at most one ends per window unless the simulation diverges twice).
    fresh = jax.lax.stop_gradient(p.v_reset(jax.random.split(k_reset, N)))
    noise = jax.random.normal(k_noise, (h, N, p.act_size))
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

    zeros = jnp.zeros((N,))
    (s_end, t_end, _, _), (obs, rew, v_next, bnd, contrib) = jax.lax.scan(
        step, (env_state, ep_step, zeros, jnp.ones((N,))), (noise, jnp.arange(h)))
    loss = -jnp.sum(contrib) / (h * N)
    return loss, (jax.lax.stop_gradient(s_end), t_end, obs, rew, v_next, bnd)


def critic_update(p: Parts, params, opt, obs, targets, key):
    """``critic_iterations`` passes of ``critic_minibatches`` shuffled minibatches regressing the
    critic on the window's targets (SHAC Sec. 3.3, Eq. 4; ``twinrl.learn.critic.minibatch_fit``);
    returns ``(params, opt, last pass's mean loss)``."""
    c, nh = p.config, int(p.config.num_envs) * int(p.config.horizon)
    return minibatch_fit(p.critic.apply, p.critic_tx, params, opt, obs.reshape(nh, p.obs_size),
                         targets.reshape(nh), key, c.critic_iterations, c.critic_minibatches)


def epoch_step(p: Parts, s: SHACState):
    """One epoch of Algorithm 1 (actor, critic, target critic, observation statistics):
    ``(next state, metrics, evaluation key)``."""
    c = p.config
    key, k_actor, k_critic, k_eval = jax.random.split(s.rng, 4)
    (loss, aux), grads = jax.value_and_grad(
        lambda *a: actor_loss(p, *a), has_aux=True)(
        s.actor, s.target_critic, s.env_state, s.ep_step, s.obs_norm, k_actor)
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
    mesh = batch_mesh()
    if N % mesh.devices.size:
        raise ValueError(f"num_envs = {N} must be a multiple of the device count "
                         f"{mesh.devices.size}")
    p = make_parts(env, c)
    state, log, done = resume(restore, init_state(p, rng), SHACState)
    # Environments split over the devices, everything else replicated, in and out of the epoch.
    state, epoch_fn = jit_sharded_epoch(lambda s: epoch_step(p, s), state, mesh,
                                        ("env_state", "ep_step"), 3)
    evaluate = make_evaluator(env, p.policy.apply, c.eval_episodes, p.episode_length)

    def epoch(e, state):
        state, m, k_eval = epoch_fn(state)
        ret = jnp.mean(evaluate(deployed(state), k_eval))
        return state, dict(env_steps=(e + 1) * N * h, **{"return": ret}, **m)

    state = run_epochs(state, log, done, c.epochs, epoch, progress_fn=progress_fn,
                       checkpoint_fn=checkpoint_fn)
    return p.policy, deployed(state), log.as_dict()
