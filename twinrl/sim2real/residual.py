"""Residual policy: adapt a simulator-trained policy on the real system without forgetting it.

SAM-RL (Lv et al., Sec. 3.4) closes the gap left after Real2Sim with a residual policy on top of
the policy learned in simulation, initialised to output zero so that the first real deployment is
exactly the simulator's policy:

    a = clip(pi_sim(o) + delta_phi(o, pi_sim(o)), -1, 1),     |delta| <= scale,

with ``delta``'s last layer zero (``twinrl.learn.networks.NetworkConfig(zero_last=True)``) and a
tanh output scaled by ``scale``, so the action bounds are respected by construction.

**How delta is trained, and why.** Two options were open: off-policy model-free RL on the
recorded real transitions, or analytic gradients through the hybrid model
(``twinrl.sim2real.hybrid``: identified simulator + learned residual dynamics, fitted to those same
transitions). We take the second. The few real episodes a round records are far too little data for
an off-policy critic (SAC/TD3 need 10^4-10^5 transitions on these tasks, ``bench/sim2real.py``),
whereas the hybrid model already condenses them into a differentiable dynamics whose one-step error
on held-out real episodes is reported, and its gradients are the same machinery the rest of twinrl
uses. Concretely: start states are the *recorded real states* (``Env.state_from_obs`` of the
dataset's observations), the combined policy is rolled out for ``horizon`` steps through the
hybrid dynamics, and ``delta``'s parameters follow the gradient of the summed reward (SHAC-style
short-horizon BPTT, Xu et al. Sec. 3.2), with a penalty on ``|delta|^2`` that keeps the residual
small where the model is unsure and the standard clipping / NaN guard.

**The acceptance gate.** That objective (a short return from recorded, mostly exciting, states) is
not the task's, and the two can disagree badly. Measured on the cartpole real twin, seed 1: the
trained delta raised the 40-step model return from the recorded states (7.25 -> 8.25) but cut the
full-episode return from the task's own initial states from 168.0 to 101.4 in the model, and
the real return from 165.2 to 77.1. ``accept`` therefore compares, through the same hybrid
dynamics, full episodes from the task's initial-state distribution with and without delta; and,
since the hybrid model can be wrong in closed loop (fitted to exciting episodes, it may never have
seen the states a good policy visits), through the identified simulator as well. The loop deploys
delta only when it lowers neither (the simulator's by at most 1 %), else the exact ``pi_sim``
(zero delta).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from twinrl.learn.common import vmap_scan
from twinrl.learn.networks import Network, NetworkConfig, make_network
from twinrl.physics.gradients import global_norm, hygiene

__all__ = ["ResidualConfig", "ResidualPolicy", "make_residual", "train", "model_return", "accept",
           "Verdict", "train_gated"]


@dataclasses.dataclass(frozen=True)
class ResidualConfig:
    """The residual network and its training through the hybrid model."""

    hidden: tuple[int, ...] = (32, 32)
    """Hidden widths of ``delta``."""
    scale: float = 0.3
    """Largest correction ``|delta|`` per action dimension (tanh output times ``scale``)."""
    horizon: int = 40
    """Steps of each differentiable rollout through the hybrid model."""
    batch_size: int = 64
    """Start states per gradient step (drawn from the recorded real states)."""
    steps: int = 150
    """Gradient steps."""
    learning_rate: float = 1e-3
    """Adam step size."""
    max_grad_norm: float = 1.0
    """Global-norm clip of each update (the NaN guard runs first)."""
    l2: float = 0.1
    """Weight of the mean ``|delta|^2`` penalty per step (in reward units)."""
    starts: str = "recorded"
    """Where the rollouts start: ``"recorded"``, the recorded real states (``train``'s
    ``start_obs``); ``"reset"``, the task's initial states (``env.reset``, fresh each step), for
    a residual whose job is the task's episode from its start, as ``accept`` judges it. On
    needle threading (twin 2's loop), 20-step rollouts from the exciting motions' states raised
    that objective (8.9 -> 12.6) and lowered the full episode's return from the task's starts
    (36.3 -> 35.5 through the hybrid model, 37.0 -> 35.1 through the identified twin):
    rejected."""

    def __post_init__(self):
        object.__setattr__(self, "hidden", tuple(int(h) for h in self.hidden))
        if self.starts not in ("recorded", "reset"):
            raise ValueError(f"ResidualConfig.starts must be 'recorded' or 'reset', got "
                             f"{self.starts!r}")
        for name in ("scale", "horizon", "batch_size", "steps", "learning_rate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ResidualConfig.{name} must be > 0, got {getattr(self, name)}")


class ResidualPolicy(NamedTuple):
    """``pi_sim`` plus ``delta``; ``act(res_params, obs)`` is the deployed action."""

    base: Network
    base_params: Any
    delta: Network

    def correction(self, res_params, obs):
        base = self.base.apply(self.base_params, obs)
        return self.delta.apply(res_params, jnp.concatenate([obs, base], -1)), base

    def act(self, res_params, obs):
        d, base = self.correction(res_params, obs)
        return jnp.clip(base + d, -1.0, 1.0)


def make_residual(base: Network, base_params, config: ResidualConfig = ResidualConfig()
                  ) -> ResidualPolicy:
    """A residual policy on ``base`` whose correction is exactly zero at initialisation."""
    delta = make_network(base.in_size + base.out_size, base.out_size,
                         NetworkConfig(hidden=config.hidden, activation="tanh", output="tanh",
                                       zero_last=True, output_scale=config.scale))
    return ResidualPolicy(base, base_params, delta)


def train(env, dynamics: Callable, policy: ResidualPolicy, start_obs: np.ndarray,
          config: ResidualConfig = ResidualConfig(), rng: jax.Array | None = None,
          res_params=None, progress_fn: Callable[[int, dict], None] | None = None
          ) -> tuple[Any, dict[str, list[float]]]:
    """Train ``delta`` through ``dynamics`` (the hybrid model's ``(state, action) -> State``) from
    recorded real observations ``start_obs`` (N, obs_size), or from the task's initial states
    (``config.starts == "reset"``; ``start_obs`` is then only checked). Returns
    ``(res_params, metrics)``; metrics hold per-step ``objective``, ``grad_norm``,
    ``delta_rms`` and the count ``skipped``.
    """
    rng = jax.random.key(0) if rng is None else rng
    start_obs = np.asarray(start_obs, np.float32)
    if start_obs.ndim != 2 or start_obs.shape[1] != env.observation_size or len(start_obs) == 0:
        raise ValueError(f"start_obs must have shape (N >= 1, {env.observation_size}), "
                         f"got {start_obs.shape}")
    if not np.isfinite(start_obs).all():
        raise ValueError("start_obs holds non-finite values")
    k_init, rng = jax.random.split(rng)
    if res_params is None:
        res_params = policy.delta.init(k_init)
    qpos0, qvel0 = env.state_from_obs(jnp.asarray(start_obs))
    rollout = _rollout_fn(env, dynamics, policy, config.horizon)

    def starts(key):
        if config.starts == "reset":
            s = jax.vmap(env.reset)(jax.random.split(key, config.batch_size)).pipeline_state
            return s.qpos, s.qvel
        idx = jax.random.randint(key, (config.batch_size,), 0, len(start_obs))
        return qpos0[idx], qvel0[idx]

    def objective(p, key):
        r, d2 = rollout(p, *starts(key))
        value = r.sum(-1) - config.l2 * d2.sum(-1)
        return -jnp.mean(value), (jnp.mean(value), jnp.sqrt(jnp.mean(d2)))

    tx = optax.chain(hygiene(config.max_grad_norm), optax.adam(config.learning_rate))
    opt_state = tx.init(res_params)

    @jax.jit
    def update(p, s, key):
        (_, (value, rms)), g = jax.value_and_grad(objective, has_aux=True)(p, key)
        finite = jnp.isfinite(global_norm(g))
        u, s = tx.update(g, s, p)
        return optax.apply_updates(p, u), s, value, global_norm(g), rms, ~finite

    metrics: dict[str, list[float]] = {"step": [], "objective": [], "grad_norm": [],
                                       "delta_rms": []}
    skipped = 0
    for i, key in enumerate(jax.random.split(rng, config.steps)):
        res_params, opt_state, value, gn, rms, bad = update(res_params, opt_state, key)
        skipped += int(bad)
        row = {"step": i, "objective": float(value), "grad_norm": float(gn),
               "delta_rms": float(rms)}
        for k, v in row.items():
            metrics[k].append(v)
        if progress_fn is not None:
            progress_fn(i, row)
    metrics["skipped"] = [float(skipped)]
    return res_params, metrics


def _rollout_fn(env, dynamics, policy: ResidualPolicy, horizon: int):
    """``(res_params, qpos (B, nq), qvel (B, nv)) -> (rewards (B, H), mean |delta|^2 per step
    (B, H))`` of the combined policy through ``dynamics`` from each state."""
    template = env.reset(jax.random.key(0))

    def start(qpos, qvel):
        return template.replace(pipeline_state=env.sim.init(qpos, qvel),
                                obs=env.observe(qpos, qvel))

    def rollouts(p, qpos, qvel):
        def body(s, _, __):
            d, base = policy.correction(p, s.obs)
            s2 = dynamics(s, jnp.clip(base + d, -1.0, 1.0))
            return s2, (s2.reward, jnp.mean(d ** 2))

        return vmap_scan(body, jax.vmap(start)(qpos, qvel), length=horizon)[1]

    return rollouts


def model_return(env, dynamics, policy: ResidualPolicy, res_params, start_obs: np.ndarray,
                 horizon: int) -> float:
    """Mean ``horizon``-step return of the combined policy through ``dynamics`` from every
    recorded observation in ``start_obs`` (deterministic: the before/after measure of training)."""
    qpos0, qvel0 = env.state_from_obs(jnp.asarray(np.asarray(start_obs, np.float32)))
    return _mean_return_fn(env, dynamics, policy, horizon)(res_params, qpos0, qvel0)


def _mean_return_fn(env, dynamics, policy: ResidualPolicy, horizon: int):
    """``(res_params, qpos (B, nq), qvel (B, nv)) -> float``: mean ``horizon``-step return of the
    combined policy through ``dynamics`` from each state (compiled once, reusable)."""
    f = jax.jit(_rollout_fn(env, dynamics, policy, horizon))
    return lambda p, qpos, qvel: float(jnp.mean(f(p, qpos, qvel)[0].sum(-1)))


class Verdict(NamedTuple):
    """``accept``'s answer: whether delta is deployed, and the mean full-episode returns without
    and with it through the hybrid model and (when given) the reference model."""

    accepted: bool
    before: float
    after: float
    reference_before: float | None = None
    reference_after: float | None = None


def accept(env, dynamics, policy: ResidualPolicy, res_params, rng: jax.Array,
           episodes: int = 16, reference: Callable | None = None,
           tolerance: float = 0.01) -> Verdict:
    """Whether the trained residual keeps or raises the task's return: ``episodes`` full episodes
    (``env.episode_length`` steps) from the task's own initial states (``env.reset``), with
    ``delta`` and without (zero), through ``dynamics`` (the hybrid model it was trained in) and,
    when given, through ``reference`` too (the loop passes the identified simulator, ``env.step``).

    Accepted when the return through ``dynamics`` does not fall, and the one through
    ``reference`` falls by at most ``tolerance`` of its magnitude: two models of the same real
    system, and delta must do no harm in either. One is not enough: a hybrid model fitted to one
    exciting pendulum episode predicted pi_sim's return as 44 where the real twin gave 190 (the
    identified simulator: 190); delta raised the model's 44 to 53, lowered the simulator's 190 to
    149, and lowered the real return to 150."""
    if not 0.0 <= tolerance < 1.0:
        raise ValueError(f"tolerance must be in [0, 1), got {tolerance}")
    states = jax.vmap(env.reset)(jax.random.split(rng, episodes))
    qpos0, qvel0 = states.pipeline_state.qpos, states.pipeline_state.qvel
    zero = jax.tree_util.tree_map(jnp.zeros_like, res_params)
    mean_return = _mean_return_fn(env, dynamics, policy, env.episode_length)  # one compile
    before, after = (mean_return(p, qpos0, qvel0) for p in (zero, res_params))
    ok = bool(np.isfinite(after) and after >= before)
    if reference is None:
        return Verdict(ok, before, after)
    ref_return = _mean_return_fn(env, reference, policy, env.episode_length)
    ref_before, ref_after = (ref_return(p, qpos0, qvel0) for p in (zero, res_params))
    ok = ok and bool(np.isfinite(ref_after)
                     and ref_after >= ref_before - tolerance * abs(ref_before))
    return Verdict(ok, before, after, ref_before, ref_after)


def train_gated(env, dynamics, policy: ResidualPolicy, start_obs: np.ndarray,
                config: ResidualConfig = ResidualConfig(), seed: int = 0,
                tolerance: float = 0.01) -> tuple[Any, dict[str, float], Verdict]:
    """What a loop deploys: ``train`` (key ``seed``), then ``accept`` (key ``seed + 1``; the
    reference is ``env.step``, the identified simulator). Returns ``(res_params, metrics,
    verdict)``: the trained parameters if accepted, else all zeros (``tanh(0) = 0``: exactly
    ``pi_sim``); ``metrics`` the training's last row with ``accepted`` and the verdict's returns
    (``model_return_*`` through ``dynamics``, ``sim_return_*`` through ``env.step``)."""
    res_params, metrics = train(env, dynamics, policy, start_obs, config, jax.random.key(seed))
    verdict = accept(env, dynamics, policy, res_params, jax.random.key(seed + 1),
                     reference=env.step, tolerance=tolerance)
    if not verdict.accepted:
        res_params = jax.tree_util.tree_map(jnp.zeros_like, res_params)
    last = {k: v[-1] for k, v in metrics.items()}
    last.update(accepted=float(verdict.accepted), model_return_before=verdict.before,
                model_return_after=verdict.after, sim_return_before=verdict.reference_before,
                sim_return_after=verdict.reference_after)
    return res_params, last, verdict
