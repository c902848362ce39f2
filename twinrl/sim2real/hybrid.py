"""Hybrid dynamics: the identified simulator plus a learned residual, trained on real transitions.

After system identification some of the reality gap is left that ``PhysParams`` cannot express
(an effect the model lacks, or parameters the data could not pin down). The Hybrid Differentiable
Simulation study closes it with a dynamics model learned from real data and mixes rollouts
through that model into policy learning (its HDS, ``twinrl.learn.hds``, fraction beta). Here the
model is *hybrid*: the differentiable simulator with identified parameters predicts the next
state and a small MLP predicts what it gets wrong,

    s_{t+1} = sim(s_t, a_{t-L}; params) + D * f_theta(normalise(o_t, a_{t-L}))

with ``D`` the per-dimension scale of the residuals in the training data, ``L`` the identified
action latency, and ``f``'s last layer initialised to zero, so the untrained hybrid *is* the
simulator. Composed this way the model stays differentiable (gradients flow through both the
simulator and the MLP), and it extrapolates like the physics where the data are thin rather than
like an unconstrained network.

Training data are the recorded transitions ``(o_t, a_t, o_{t+1})``: states come from
``Env.state_from_obs``; angle residuals of hinge joints are wrapped into (-pi, pi]. The fit holds
out a fraction of *episodes* (not transitions) for validation and keeps the parameters with the
best validation loss; ``HybridFit`` reports the one-step error of the simulator alone and of the
hybrid on the held-out episodes. ``save``/``load`` keep a fitted model as a checkpoint.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import optax

from twinrl.envs.wrappers import QUEUE_KEY
from twinrl.learn.networks import Network, NetworkConfig, make_network

__all__ = ["HybridConfig", "HybridModel", "HybridFit", "Transitions", "transitions",
           "applied_actions", "fit", "save", "load", "make_dynamics", "one_step_errors"]


@dataclasses.dataclass(frozen=True)
class HybridConfig:
    """How the residual dynamics network is built and fitted."""

    hidden: tuple[int, ...] = (64, 64)
    """Hidden layer widths of the residual MLP."""
    activation: str = "swish"
    """Hidden activation (``twinrl.learn.networks.ACTIVATIONS``)."""
    learning_rate: float = 3e-3
    """Adam step size."""
    weight_decay: float = 1e-4
    """Decoupled weight decay (AdamW): keeps the residual small where the data say little."""
    steps: int = 1500
    """Gradient steps."""
    batch_size: int = 256
    """Transitions per gradient step (sampled with replacement)."""
    val_fraction: float = 0.2
    """Fraction of episodes held out for validation / early stopping (at least one episode when
    there are two or more)."""
    eval_every: int = 50
    """Steps between validation evaluations."""

    def __post_init__(self):
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        for name in ("learning_rate", "steps", "batch_size", "eval_every"):
            if not getattr(self, name) > 0:
                raise ValueError(f"HybridConfig.{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(f"HybridConfig.val_fraction must be in [0, 1), got {self.val_fraction}")


class Transitions(NamedTuple):
    """Recorded transitions as simulator states: ``(qpos, qvel) --applied--> (qpos2, qvel2)``."""

    obs: np.ndarray
    applied: np.ndarray
    """The action the system actually executed at each step (latency applied)."""
    qpos: np.ndarray
    qvel: np.ndarray
    qpos2: np.ndarray
    qvel2: np.ndarray
    episode: np.ndarray


class HybridModel(NamedTuple):
    """A fitted residual: ``network`` with ``params`` and the normalisation it was trained with."""

    network: Network
    params: Any
    in_mean: jax.Array
    in_std: jax.Array
    out_scale: jax.Array
    latency: int

    def residual(self, obs: jax.Array, applied: jax.Array) -> jax.Array:
        """``(Δqpos, Δqvel)`` concatenated, for one observation and executed action."""
        x = (jnp.concatenate([obs, applied], -1) - self.in_mean) / self.in_std
        return self.out_scale * self.network.apply(self.params, x)


class HybridFit(NamedTuple):
    model: HybridModel
    metrics: dict[str, Any]
    """``sim_val_rmse`` and ``hybrid_val_rmse`` (per state dimension, in the state's units, on the
    held-out episodes), ``train_loss``/``val_loss`` history, ``best_step``, counts."""


def applied_actions(actions: np.ndarray, episode: np.ndarray, latency: int) -> np.ndarray:
    """The actions a system with ``latency`` steps of delay executed: ``a_{t-L}`` within each
    episode, zeros for its first ``L`` steps (as ``RealTwin`` does)."""
    actions = np.asarray(actions)
    if latency < 0:
        raise ValueError(f"latency must be >= 0 steps, got {latency}")
    if latency == 0:
        return actions.copy()
    out = np.zeros_like(actions)
    for ep in np.unique(episode):
        idx = np.flatnonzero(episode == ep)
        out[idx[latency:]] = actions[idx[:-latency]] if len(idx) > latency else 0
    return out


def _hinge_dims(model: mujoco.MjModel) -> np.ndarray:
    dims = [model.jnt_qposadr[j] for j in range(model.njnt)
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    mask = np.zeros(model.nq, bool)
    mask[np.asarray(dims, int)] = True
    return mask


def _wrap(d: jax.Array, mask) -> jax.Array:
    return jnp.where(mask, jnp.arctan2(jnp.sin(d), jnp.cos(d)), d)


def transitions(env, data, latency: int = 0) -> Transitions:
    """Simulator-state transitions from a ``twinrl.real.dataset.Dataset`` (or anything with
    ``obs``, ``action``, ``next_obs``, ``episode_id`` arrays). Non-finite or mis-shaped data raise
    a ``ValueError`` naming the array."""
    obs = np.asarray(data.obs, np.float64)
    act = np.asarray(data.action, np.float64)
    nxt = np.asarray(data.next_obs, np.float64)
    episode = np.asarray(getattr(data, "episode_id", np.zeros(len(obs), int)))
    n = len(obs)
    for name, arr, width in (("obs", obs, env.observation_size),
                             ("next_obs", nxt, env.observation_size),
                             ("action", act, env.action_size)):
        if arr.ndim != 2 or arr.shape != (n, width):
            raise ValueError(f"{name} must have shape ({n}, {width}) for {env.name}, "
                             f"got {arr.shape}")
        bad = ~np.isfinite(arr).all(axis=1)
        if bad.any():
            raise ValueError(f"{name} holds non-finite values at transition(s) "
                             f"{np.flatnonzero(bad)[:5].tolist()}")
    if n == 0:
        raise ValueError("no transitions to learn from")
    qpos, qvel = (np.asarray(x, np.float64) for x in env.state_from_obs(obs))
    qpos2, qvel2 = (np.asarray(x, np.float64) for x in env.state_from_obs(nxt))
    return Transitions(obs, applied_actions(act, episode, latency), qpos, qvel, qpos2, qvel2,
                       episode)


def _validation_split(episode: np.ndarray, fraction: float, rng: jax.Array
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``(is_val mask, held-out episode ids)``: ``fraction`` of the episodes (at least one when
    there are two or more), drawn by ``rng``; from a single episode, its last ``fraction`` of
    transitions (a contiguous block, so the network is stopped on states it was not fitted to,
    not on its own training data: fitted and judged on the same 250 transitions, a pendulum
    residual lowered its training error by a third and cut pi_sim's full-episode return through
    the hybrid model from 190 to 44)."""
    episodes = np.unique(episode)
    if fraction <= 0 or len(episode) < 2:
        return np.zeros(len(episode), bool), np.zeros(0, int)
    if len(episodes) == 1:
        n_val = min(len(episode) - 1, max(1, int(round(fraction * len(episode)))))
        is_val = np.zeros(len(episode), bool)
        is_val[-n_val:] = True
        return is_val, np.zeros(0, int)
    n_val = max(1, int(round(fraction * len(episodes))))
    perm = np.random.default_rng(int(jax.random.randint(rng, (), 0, 2**31 - 1))).permutation(
        episodes)
    val_eps = perm[:n_val]
    is_val = np.isin(episode, val_eps)
    if not (~is_val).any():
        is_val[:] = False
    return is_val, val_eps


def _sim_next(env, params):
    """``(qpos, qvel, applied) -> (qpos', qvel')`` of the simulator, one control step."""
    def f(qpos, qvel, applied):
        data = env.sim.init(qpos, qvel)
        data = env.sim_step(data, applied, params)
        return data.qpos, data.qvel
    return f


def fit(env, data, params=None, latency: int = 0, config: HybridConfig = HybridConfig(),
        rng: jax.Array | None = None, progress_fn: Callable[[int, dict], None] | None = None
        ) -> HybridFit:
    """Fit the residual of ``env``'s simulator under ``params`` (identified ``PhysParams``; None:
    the env's own) to recorded transitions ``data``."""
    rng = jax.random.key(0) if rng is None else rng
    params = env.params if params is None else params
    tr = transitions(env, data, latency)
    mask = _hinge_dims(env.sim.mj_model)
    sim_next = jax.jit(jax.vmap(_sim_next(env, params)))
    pq, pv = (np.asarray(x, np.float64) for x in sim_next(
        jnp.asarray(tr.qpos, jnp.float32), jnp.asarray(tr.qvel, jnp.float32),
        jnp.asarray(tr.applied, jnp.float32)))
    target = np.concatenate([np.asarray(_wrap(tr.qpos2 - pq, mask)), tr.qvel2 - pv], -1)
    x = np.concatenate([tr.obs, tr.applied], -1)

    is_val, val_eps = _validation_split(tr.episode, config.val_fraction, rng)
    train_idx, val_idx = np.flatnonzero(~is_val), np.flatnonzero(is_val)

    in_mean = x[train_idx].mean(0)
    in_std = x[train_idx].std(0) + 1e-6
    out_scale = target[train_idx].std(0) + 1e-8
    net = make_network(x.shape[1], target.shape[1],
                       NetworkConfig(hidden=config.hidden, activation=config.activation,
                                     output="linear", zero_last=True))
    k_init, k_batch = jax.random.split(rng)
    theta = net.init(k_init)
    X = jnp.asarray((x - in_mean) / in_std, jnp.float32)
    Y = jnp.asarray(target / out_scale, jnp.float32)
    tx = optax.adamw(config.learning_rate, weight_decay=config.weight_decay)
    opt_state = tx.init(theta)

    def loss(p, idx):
        return jnp.mean((net.apply(p, X[idx]) - Y[idx]) ** 2)

    @jax.jit
    def update(p, s, key):
        idx = jax.random.choice(key, jnp.asarray(train_idx), (config.batch_size,))
        value, g = jax.value_and_grad(loss)(p, idx)
        u, s = tx.update(g, s, p)
        return optax.apply_updates(p, u), s, value

    eval_idx = jnp.asarray(val_idx if len(val_idx) else train_idx)
    val_loss = jax.jit(lambda p: loss(p, eval_idx))
    best = (float(val_loss(theta)), 0, theta)
    history = {"step": [0], "train_loss": [float(loss(theta, jnp.asarray(train_idx)))],
               "val_loss": [best[0]]}
    keys = jax.random.split(k_batch, config.steps)
    for i in range(config.steps):
        theta, opt_state, tl = update(theta, opt_state, keys[i])
        if (i + 1) % config.eval_every == 0 or i + 1 == config.steps:
            vl = float(val_loss(theta))
            history["step"].append(i + 1)
            history["train_loss"].append(float(tl))
            history["val_loss"].append(vl)
            if np.isfinite(vl) and vl < best[0]:
                best = (vl, i + 1, theta)
            if progress_fn is not None:
                progress_fn(i + 1, {"train_loss": float(tl), "val_loss": vl})
    model = HybridModel(net, best[2], jnp.asarray(in_mean, jnp.float32),
                        jnp.asarray(in_std, jnp.float32), jnp.asarray(out_scale, jnp.float32),
                        int(latency))
    ev = val_idx if len(val_idx) else train_idx
    pred = np.asarray(jax.vmap(model.residual)(jnp.asarray(tr.obs[ev], jnp.float32),
                                               jnp.asarray(tr.applied[ev], jnp.float32)))
    metrics = {
        "sim_val_rmse": np.sqrt(np.mean(target[ev] ** 2, 0)).tolist(),
        "hybrid_val_rmse": np.sqrt(np.mean((target[ev] - pred) ** 2, 0)).tolist(),
        "best_step": best[1], "train_transitions": len(train_idx),
        "val_transitions": len(val_idx), "val_episodes": [int(e) for e in val_eps],
        **history,
    }
    return HybridFit(model, metrics)


def save(path, fit_result: HybridFit):
    """Write a fitted model to ``path`` as a policy checkpoint (``twinrl.learn.checkpoint``) of
    kind ``hybrid_residual``: the network's params, its normalisation, latency and fit metrics in
    JSON, so ``load`` rebuilds it without refitting (the loop's ``hybrid`` stage artefact)."""
    from twinrl.learn.checkpoint import save_policy

    m = fit_result.model
    return save_policy(path, m.network, m.params, kind="hybrid_residual", in_mean=m.in_mean,
                       in_std=m.in_std, out_scale=m.out_scale, latency=m.latency,
                       metrics=fit_result.metrics)


def load(path) -> HybridModel:
    """The ``HybridModel`` ``save`` wrote to ``path``."""
    from twinrl.learn.checkpoint import load_policy

    net, params, meta = load_policy(path)
    f32 = lambda k: jnp.asarray(np.asarray(meta[k]), jnp.float32)  # noqa: E731
    return HybridModel(net, params, f32("in_mean"), f32("in_std"), f32("out_scale"),
                       int(meta["latency"]))


def make_dynamics(env, model: HybridModel) -> Callable:
    """``dynamics(state, action) -> State``: ``env.step`` (the simulator with ``env.params``, i.e.
    build ``env`` with the identified parameters) plus the hybrid model's correction: the drop-in
    replacement that ``twinrl.learn.hds.train(..., dynamics=...)`` mixes in.

    The residual was fitted on executed (applied) actions, so it corrects the dynamics, not the
    delay: on a bare ``env`` the executed action is the policy's; on an env that delays actions
    (``envs.make(name, system=...)`` with a latency) it is the one leaving the delay's queue now.
    """
    nq = env.sim.nq

    def dynamics(state, action):
        action = jnp.asarray(action, jnp.float32).reshape(env.action_size)
        data = state.pipeline_state
        # the wrapper's own view of the queue (emptied after an auto-reset), so model and
        # simulator agree on what was executed
        executed = env.executed(state) if QUEUE_KEY in state.info else action
        d = model.residual(env.observe(data.qpos, data.qvel), jnp.clip(executed, -1.0, 1.0))
        stepped = env.step(state, action)
        nd = stepped.pipeline_state.replace(qpos=stepped.pipeline_state.qpos + d[:nq],
                                            qvel=stepped.pipeline_state.qvel + d[nq:])
        reward, terms = env.reward(nd.qpos, nd.qvel, action)
        metrics = dict(stepped.metrics)
        metrics.update({f"reward/{k}": v for k, v in terms.items()})
        return stepped.replace(pipeline_state=nd, obs=env.observe(nd.qpos, nd.qvel),
                               reward=reward, metrics=metrics)

    return dynamics


def one_step_errors(env, model: HybridModel | None, data, params=None) -> np.ndarray:
    """Per-dimension RMSE of one-step predictions of ``data`` by the simulator (``model`` None) or
    the hybrid model."""
    params = env.params if params is None else params
    latency = model.latency if model is not None else 0
    tr = transitions(env, data, latency)
    mask = _hinge_dims(env.sim.mj_model)
    sim_next = jax.jit(jax.vmap(_sim_next(env, params)))
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    pq, pv = (np.asarray(v, np.float64) for v in sim_next(f32(tr.qpos), f32(tr.qvel),
                                                          f32(tr.applied)))
    if model is not None:
        d = np.asarray(jax.vmap(model.residual)(f32(tr.obs), f32(tr.applied)), np.float64)
        pq, pv = pq + d[:, :env.sim.nq], pv + d[:, env.sim.nq:]
    err = np.concatenate([np.asarray(_wrap(tr.qpos2 - pq, mask)), tr.qvel2 - pv], -1)
    return np.sqrt(np.mean(err ** 2, 0))
