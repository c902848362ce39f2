"""Model-free and analytic-gradient baselines: Brax's PPO and APG on our tasks, unpatched.

The differentiable trainers (``pods``, ``hds``, ``shac``) are measured against

- **PPO** (Schulman et al. 2017), ``brax.training.agents.ppo``: model-free, on-policy, the usual
  sample-hungry but robust reference;
- **APG** (analytic policy gradients, Brax's ``brax.training.agents.apg``): backpropagation through
  the simulator over a fixed horizon *without* a critic -- the ablation that shows what SHAC's
  value bootstrap (Xu et al. ICLR 2022, Sec. 3.2) buys.

Both are Brax's own trainers on the pinned brax 0.14.2 / jax 0.9.2; our ``Env`` is a Brax env, so
they take it unmodified. ``ppo_train`` and ``apg_train`` wrap them in our contract as far as it
goes (``twinrl.learn.common``): ``(env, config, rng, *, progress_fn) -> (policy, params,
metrics)`` where ``policy.apply(params, obs)`` is the *deterministic* action (the mode of Brax's
tanh-Gaussian, ``tanh(loc)``) after Brax's observation normaliser, so ``make_evaluator`` scores it
like any of ours. ``params`` is a plain dict ``{"obs_mean", "obs_std", "policy"}``: what a
deployed policy needs (the PPO value network is dropped), and with the JSON of the config
(``config.to_dict()``) ``ppo_policy``/``apg_policy`` (``twinrl.learn.brax_policies``, re-exported
here) rebuild ``policy`` without the training code: the returned policy carries that JSON as
``policy.spec``, and ``NETWORK_KINDS`` gives
``twinrl.learn.checkpoint.load_policy`` the builders of the kinds ``brax_ppo``/``brax_apg``, so
``save_policy``/``load_policy`` round-trip it.

Metrics: one entry per Brax evaluation (``progress_fn`` call), with ``epoch`` (evaluation index),
``env_steps``, ``wall_s`` (since ``*_train`` was called, compile included), ``return`` (Brax's
deterministic evaluation: mean episode return over ``num_eval_envs`` full episodes) and, where Brax
reports them, its training losses. Brax's trainers keep their state in closures, so runs cannot be
resumed: passing ``checkpoint_fn`` or ``restore`` raises ``NotImplementedError``.

Tuned settings for our 250-step swing-ups (per-step reward in [0, 1]) are
``twinrl.learn.tuned.TUNED["ppo"|"apg"][task]`` (applied by ``twinrl.learn.runner.make_config``;
``ppo_config(task)``/``apg_config(task)`` here).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from brax.training.agents.apg import train as apg
from brax.training.agents.ppo import train as ppo

from twinrl.learn import distributed, tuned
from twinrl.learn.common import JSONConfig, MetricLog, ProgressFn
from twinrl.learn.brax_policies import (BraxPolicy, apg_policy, make_apg_nets, make_ppo_nets,
                                        ppo_policy)
from twinrl.learn.networks import ACTIVATIONS, Network

__all__ = ["PPOConfig", "APGConfig", "ppo_train", "apg_train", "ppo_policy", "apg_policy",
           "ppo_config", "apg_config", "BraxPolicy", "NETWORK_KINDS"]


@dataclasses.dataclass(frozen=True)
class PPOConfig(JSONConfig):
    """Brax PPO's settings (names as in ``brax.training.agents.ppo.train.train``)."""

    num_timesteps: int = 3_000_000
    """Environment steps to train for (Brax rounds up to whole training iterations)."""
    num_envs: int = 256
    """Environments stepped in parallel."""
    batch_size: int = 256
    """Trajectories (of ``unroll_length`` steps) per SGD minibatch."""
    num_minibatches: int = 8
    """Minibatches per collected batch; ``batch_size * num_minibatches`` must be a multiple of
    ``num_envs``."""
    unroll_length: int = 32
    """Steps per collected trajectory segment (the GAE window)."""
    num_updates_per_batch: int = 4
    """SGD passes over each collected batch."""
    learning_rate: float = 1e-3
    """Adam learning rate."""
    entropy_cost: float = 1e-2
    """Entropy bonus weight (exploration)."""
    discounting: float = 0.97
    """Discount factor."""
    gae_lambda: float = 0.95
    """GAE lambda."""
    clipping_epsilon: float = 0.2
    """PPO's ratio clip."""
    reward_scaling: float = 1.0
    """Multiplies rewards inside the loss."""
    max_grad_norm: float | None = 1.0
    """Global-norm gradient clip (None: none)."""
    normalize_observations: bool = True
    """Running mean/std observation normaliser (part of the deployed policy)."""
    policy_hidden: tuple[int, ...] = (64, 64)
    """Policy MLP hidden widths."""
    value_hidden: tuple[int, ...] = (128, 128)
    """Value MLP hidden widths."""
    activation: str = "swish"
    """Hidden activation of both networks (``twinrl.learn.networks.ACTIVATIONS``)."""
    episode_length: int | None = None
    """Time limit of training and evaluation episodes; default ``env.episode_length``."""
    num_evals: int = 10
    """Evaluations (``progress_fn`` calls, metric entries), the first one before training."""
    num_eval_envs: int = 64
    """Episodes per evaluation."""

    def __post_init__(self):
        self.check_fields(
            widths=("policy_hidden", "value_hidden"), choices={"activation": ACTIVATIONS},
            at_least_one=("num_timesteps", "num_envs", "batch_size", "num_minibatches",
                          "unroll_length", "num_updates_per_batch", "num_evals", "num_eval_envs",
                          "episode_length"),
            positive=("learning_rate", "reward_scaling", "clipping_epsilon", "max_grad_norm"),
            non_negative=("entropy_cost",), within={"discounting": "[0, 1]", "gae_lambda": "[0, 1]"},
            optional=("episode_length", "max_grad_norm"))
        if (self.batch_size * self.num_minibatches) % self.num_envs:
            raise ValueError(f"PPOConfig: batch_size * num_minibatches = "
                             f"{self.batch_size * self.num_minibatches} must be a multiple of "
                             f"num_envs = {self.num_envs}")


@dataclasses.dataclass(frozen=True)
class APGConfig(JSONConfig):
    """Brax APG's settings (names as in ``brax.training.agents.apg.train.train``)."""

    policy_updates: int = 600
    """Gradient steps; each simulates ``num_envs * horizon_length`` steps and backpropagates
    through them."""
    horizon_length: int = 32
    """Steps of backpropagation through the simulator per update (Brax's default 32)."""
    num_envs: int = 64
    """Environments simulated in parallel."""
    learning_rate: float = 2e-3
    """Adam learning rate (decayed by ``schedule_decay`` per update if ``use_schedule``)."""
    use_schedule: bool = True
    """Exponential learning-rate decay."""
    schedule_decay: float = 0.997
    """Per-update decay factor."""
    max_gradient_norm: float = 1.0
    """Global-norm gradient clip."""
    normalize_observations: bool = True
    """Running mean/std observation normaliser (part of the deployed policy)."""
    policy_hidden: tuple[int, ...] = (64, 64)
    """Policy MLP hidden widths (LayerNorm after each, as Brax's APG networks)."""
    activation: str = "elu"
    """Hidden activation (``twinrl.learn.networks.ACTIVATIONS``)."""
    episode_length: int | None = None
    """Time limit of training and evaluation episodes; default ``env.episode_length``."""
    num_evals: int = 11
    """Evaluations (``progress_fn`` calls, metric entries), the first one before training."""
    num_eval_envs: int = 64
    """Episodes per evaluation."""

    def __post_init__(self):
        self.check_fields(
            widths=("policy_hidden",), choices={"activation": ACTIVATIONS},
            at_least_one=("policy_updates", "horizon_length", "num_envs", "num_evals",
                          "num_eval_envs", "episode_length"),
            positive=("learning_rate", "max_gradient_norm"), within={"schedule_decay": "(0, 1]"},
            optional=("episode_length",))
        if self.num_evals > 1 and self.policy_updates < self.num_evals - 1:
            raise ValueError(f"APGConfig.policy_updates = {self.policy_updates} must be >= "
                             f"num_evals - 1 = {self.num_evals - 1}")


def ppo_config(task: str, **overrides) -> PPOConfig:
    """PPO's config for ``task``: defaults, ``tuned.TUNED["ppo"][task]``, then ``overrides``."""
    return PPOConfig(**{**tuned.overrides("ppo", task), **overrides})


def apg_config(task: str, **overrides) -> APGConfig:
    """APG's config for ``task``: defaults, ``tuned.TUNED["apg"][task]``, then ``overrides``."""
    return APGConfig(**{**tuned.overrides("apg", task), **overrides})


# What ``twinrl.learn.checkpoint.load_policy`` rebuilds ``brax_*`` networks with. The loader looks
# this table up (importing this module when it meets such a kind) rather than this module
# registering into the loader, so the import runs one way: checkpoint -> baselines.
NETWORK_KINDS = {
    "brax_ppo": lambda spec: ppo_policy(int(spec["in_size"]), int(spec["out_size"]),
                                        PPOConfig.from_dict(spec["config"])),
    "brax_apg": lambda spec: apg_policy(int(spec["in_size"]), int(spec["out_size"]),
                                        APGConfig.from_dict(spec["config"])),
}


def _plain_params(normaliser, policy_params) -> dict[str, Any]:
    return {"obs_mean": jnp.asarray(normaliser.mean), "obs_std": jnp.asarray(normaliser.std),
            "policy": policy_params}


# ------------------------------------------------------------------------------ trainers
def _seed(rng) -> int:
    """Brax's trainers take an int seed: an int passes through, a key is turned into one."""
    if isinstance(rng, (int, np.integer)):
        return int(rng)
    if isinstance(rng, jax.Array) and jnp.issubdtype(rng.dtype, jax.dtypes.prng_key):
        rng = jax.random.key_data(rng)
    return int(jax.random.randint(jnp.asarray(rng, jnp.uint32), (), 0, 2**31 - 1))


def _refuse_resume(name, checkpoint_fn, restore):
    if checkpoint_fn is not None or restore is not None:
        raise NotImplementedError(
            f"{name}: Brax's trainer keeps its state in closures, so it cannot be checkpointed or "
            f"resumed; pass checkpoint_fn=None and restore=None (resume is supported by the "
            f"twinrl trainers pods, hds and shac)")


def _metric_row(log: MetricLog, index: int, env_steps: int, m: dict) -> dict[str, float]:
    extra = {k.split("/", 1)[1]: v for k, v in m.items()
             if k.startswith("training/") and np.ndim(v) == 0
             and k not in ("training/sps", "training/walltime")}
    return log.record(epoch=index, env_steps=env_steps,
                      **{"return": m.get("eval/episode_reward", np.nan)}, **extra)


def ppo_train(env, config: PPOConfig = PPOConfig(), rng: jax.Array | int = 0, *,
              progress_fn: ProgressFn | None = None, checkpoint_fn=None, restore=None
              ) -> tuple[Network, dict[str, Any], dict[str, list[float]]]:
    """Brax PPO on ``env``; returns ``(policy, params, metrics)`` as described in the module."""
    _refuse_resume("ppo_train", checkpoint_fn, restore)
    c = config
    T = int(c.episode_length or env.episode_length)
    log = MetricLog()
    count = [0]

    def progress(step, m):
        count[0] += 1
        row = _metric_row(log, count[0] - 1, int(step), m)
        if progress_fn is not None:
            progress_fn(count[0] - 1, row)

    nets = lambda obs_size, action_size, preprocess_observations_fn: make_ppo_nets(  # noqa: E731
        obs_size, action_size, c)
    with distributed.classic_pmap():  # Brax 0.14.2 needs it on several processes
        _, params, _ = ppo.train(
            environment=env, num_timesteps=c.num_timesteps, num_envs=c.num_envs,
            episode_length=T, batch_size=c.batch_size, num_minibatches=c.num_minibatches,
            unroll_length=c.unroll_length, num_updates_per_batch=c.num_updates_per_batch,
            learning_rate=c.learning_rate, entropy_cost=c.entropy_cost, discounting=c.discounting,
            gae_lambda=c.gae_lambda, clipping_epsilon=c.clipping_epsilon,
            reward_scaling=c.reward_scaling, max_grad_norm=c.max_grad_norm,
            normalize_observations=c.normalize_observations, network_factory=nets,
            num_evals=c.num_evals, num_eval_envs=c.num_eval_envs, deterministic_eval=True,
            use_pmap_on_reset=False, seed=_seed(rng), progress_fn=progress)
    policy = ppo_policy(int(env.observation_size), int(env.action_size), c)
    return policy, _plain_params(params[0], params[1]), log.as_dict()


def apg_train(env, config: APGConfig = APGConfig(), rng: jax.Array | int = 0, *,
              progress_fn: ProgressFn | None = None, checkpoint_fn=None, restore=None
              ) -> tuple[Network, dict[str, Any], dict[str, list[float]]]:
    """Brax APG on ``env``; returns ``(policy, params, metrics)`` as described in the module."""
    _refuse_resume("apg_train", checkpoint_fn, restore)
    if distributed.is_distributed():
        raise distributed.DistributedError(
            "Brax APG cannot run on several processes: brax 0.14.2's apg.train draws episode "
            "step counters for num_envs environments (scramble_times) where each process holds "
            "num_envs / processes; run APG on one process")
    c = config
    T = int(c.episode_length or env.episode_length)
    log = MetricLog()
    # Brax's APG: round(updates / evaluations after the first) updates between evaluations.
    per_eval = int(np.round(c.policy_updates / max(c.num_evals - 1, 1)))
    steps_per_eval = per_eval * c.num_envs * c.horizon_length

    def progress(it, m):
        row = _metric_row(log, int(it), int(it) * steps_per_eval, m)
        if progress_fn is not None:
            progress_fn(int(it), row)

    nets = lambda obs_size, action_size, preprocess_observations_fn: make_apg_nets(  # noqa: E731
        obs_size, action_size, c)
    _, params, _ = apg.train(
        environment=env, episode_length=T, policy_updates=c.policy_updates,
        horizon_length=c.horizon_length, num_envs=c.num_envs, num_evals=c.num_evals,
        num_eval_envs=c.num_eval_envs, learning_rate=c.learning_rate,
        use_schedule=c.use_schedule, schedule_decay=c.schedule_decay,
        max_gradient_norm=c.max_gradient_norm, normalize_observations=c.normalize_observations,
        deterministic_eval=True, network_factory=nets, seed=_seed(rng),
        progress_fn=progress)
    policy = apg_policy(int(env.observation_size), int(env.action_size), c)
    return policy, _plain_params(params[0], params[1]), log.as_dict()
