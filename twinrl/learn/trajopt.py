"""Trajectory optimisation: improve an action sequence with the analytic gradient of its return.

This is the inner step of PODS (Mora et al., "PODS: Policy Optimization via Differentiable
Simulation", ICML 2021, Sec. 4): every rollout's actions ``a`` (T x m) are improved with the
derivative of their return ``V(a)`` through the simulator, the improved actions are kept only if a
line search finds a better return, and the policy is then regressed onto them (``learn.pods``).
HDS and learning from demonstrations reuse the same step.

Two update directions (PODS Sec. 4.1 and 4.2):

- **first order**: ``a + alpha * dV/da``;
- **second order (Gauss–Newton)**: ``a + alpha * H^-1 dV/da``. With the states ``s_t(a)`` of the
  rollout and the per-step reward ``r(s_t, a_t)``, ``V = sum_t r(s_t, a_t)``. Linearising the
  dynamics, ``z_t = (s_t, a_t) ~ z_t(a0) + Z_t (a - a0)`` with ``Z_t = [ds_t/da ; da_t/da]``
  ((n + m) x T m), so the second-order model of the *cost* ``-V`` is
  ``H = sum_t Z_t^T (-d^2 r / dz^2)_t Z_t``, i.e. ``(ds/da)^T (-d^2V/ds^2) (ds/da) - d^2V/da^2`` plus
  the state-action cross terms; the curvature of the dynamics (second derivatives of ``s(a)``) is
  what Gauss–Newton drops. We work with the cost so that ``H`` should be positive definite; each
  per-step ``-d^2 r/dz^2`` is projected onto the positive semi-definite cone (eigenvalues clipped
  at 0: a reward that is locally convex, such as the pendulum's ``(1 - cos th) / 2`` near hanging,
  would otherwise make Newton walk *downhill*), and Levenberg–Marquardt damping ``lambda I`` makes
  the (T m) x (T m) system positive definite, solved by Cholesky for any action dimension m. (The
  research code that PODS grew from inverted an explicit Hessian and worked only for m = 1.)

**Discount and terminal value.** The objective may be the discounted window return plus a
terminal value, ``V(a) = sum_t gamma^t r(s_{t+1}, a_t) + gamma^T V_term(s_T)``
(``TrajoptConfig.discount``, and ``terminal_fn`` of every function below): the short-horizon
actor objective of SHAC (Xu et al., ICLR 2022, Sec. 3.2, Eq. 2), which lets a window of a long
episode see past its own end through a learned critic (``twinrl.learn.pods``'s ``critic``). With
``discount = 1`` and no ``terminal_fn`` it is PODS's plain return. The Gauss–Newton matrix takes
the terminal value's gradient, and its curvature at ``s_T`` only if asked
(``TrajoptConfig.terminal_curvature``).

A line search evaluates ``alpha_k = step_size * 2^-k``, k = 0..K-1, in one vmapped call on the
clipped candidates ``clip(a + alpha_k d, low, high)`` and takes the best of those whose return is
*strictly* higher than the current one; if none is, the actions are kept (``accepted = False``).
A non-finite gradient, Hessian or direction takes no step and is flagged (``nonfinite``).

The problem is given as two pure functions, so that the states the Gauss–Newton step needs are
explicit: ``rollout_fn(actions (T, m)) -> states (T, n)`` (the state *after* each action) and
``reward_fn(state (n,), action (m,)) -> scalar``; ``env_problem(env, state)`` builds them for a
``twinrl.envs.Env`` from a start ``State`` (inside a jit, so one compile serves every start state).
Everything is a pure, jit/vmap-able function of arrays. Typical use (PODS's inner loop)::

    cfg = TrajoptConfig(order=2, regularization=1e-2)
    step = jax.jit(jax.vmap(lambda s, a: improve(*env_problem(env, s), a, cfg)))
    res = step(start_states, actions)        # res.actions: regression targets for the policy
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from twinrl.envs.wrappers import QUEUE_KEY, LatencyWrapper
from twinrl.physics.gradients import all_finite, global_norm

__all__ = ["TrajoptConfig", "TrajoptResult", "RolloutFn", "RewardFn", "TerminalFn", "env_problem",
           "trajectory_return", "line_search", "first_order_direction", "gauss_newton_direction",
           "improve", "optimize"]

RolloutFn = Callable[[jax.Array], jax.Array]
"""``actions (T, m) -> states (T, n)``: the state after each action, differentiable."""
RewardFn = Callable[[jax.Array, jax.Array], jax.Array]
"""``(state (n,), action (m,)) -> reward ()``: twice differentiable for the second order."""
TerminalFn = Callable[[jax.Array], jax.Array]
"""``state (n,) -> value ()`` of the last state ``s_T``: twice differentiable for the second
order."""


@dataclasses.dataclass(frozen=True)
class TrajoptConfig:
    """How one improvement step of an action sequence is taken."""

    order: int = 1
    """1: gradient ascent direction ``dV/da``; 2: Gauss–Newton direction ``H^-1 dV/da``."""
    step_size: float = 1.0
    """``alpha0``, the largest step the line search tries (first order: in action units per unit
    of gradient; second order: 1 is the full Gauss–Newton step)."""
    line_search_steps: int = 8
    """K: step sizes ``step_size * 2^-k`` for k = 0..K-1, all evaluated in one vmapped call
    (each costs one rollout of T steps)."""
    regularization: float = 1e-3
    """Levenberg–Marquardt damping ``lambda`` added to the Gauss–Newton matrix's diagonal
    (second order only); larger is more cautious, closer to a scaled gradient step."""
    max_grad_norm: float | None = None
    """If set, the gradient is scaled to at most this global norm before the direction is formed
    (for the second order this scales the Newton step by the same factor)."""
    action_low: float = -1.0
    """Lower action bound; every candidate is clipped to it."""
    action_high: float = 1.0
    """Upper action bound; every candidate is clipped to it."""
    max_step_norm: float | None = None
    """If set, the direction (after the Gauss–Newton solve) is scaled to at most this global
    norm: a trust region. Where the reward is nearly flat in the actions (cartpole hanging down:
    the upright factor multiplies the control cost's curvature by ~0) the damped Gauss–Newton
    step is ``~ g / regularization``, far larger than a policy regressed onto it can follow."""
    discount: float = 1.0
    """gamma in (0, 1]: the reward of step t is weighted ``gamma^t`` and the terminal value
    ``gamma^T`` (module docstring); 1 is PODS's undiscounted return."""
    terminal_curvature: bool = False
    """Second order: add the terminal value's (PSD-projected) Hessian to the Gauss–Newton matrix.
    Off by default, so a learned critic enters the model linearly (its gradient only): with its
    Hessian, pods2 with a critic on ``cartpole_swingup`` (seed 0, regularization 1) stalled at a
    return of 110-125 (best 136 in 150 epochs); without it, it reached 130 at epoch 38 and 160
    at epoch 100. The curvature of a network fitted to noisy targets is no model to trust."""

    def __post_init__(self):
        if self.order not in (1, 2):
            raise ValueError(f"order must be 1 (gradient) or 2 (Gauss-Newton), got {self.order!r}")
        if not self.step_size > 0:
            raise ValueError(f"step_size must be > 0, got {self.step_size}")
        if int(self.line_search_steps) < 1 or int(self.line_search_steps) != self.line_search_steps:
            raise ValueError(f"line_search_steps must be an integer >= 1, "
                             f"got {self.line_search_steps}")
        if not self.regularization >= 0:
            raise ValueError(f"regularization must be >= 0, got {self.regularization}")
        if self.max_grad_norm is not None and not self.max_grad_norm > 0:
            raise ValueError(f"max_grad_norm must be > 0 or None, got {self.max_grad_norm}")
        if self.max_step_norm is not None and not self.max_step_norm > 0:
            raise ValueError(f"max_step_norm must be > 0 or None, got {self.max_step_norm}")
        if not 0.0 < self.discount <= 1.0:
            raise ValueError(f"discount must be in (0, 1], got {self.discount}")
        if not self.action_low < self.action_high:
            raise ValueError(f"action_low must be < action_high, got "
                             f"[{self.action_low}, {self.action_high}]")

    @property
    def alphas(self) -> jax.Array:
        """The line search's step sizes, largest first."""
        return self.step_size * 0.5 ** jnp.arange(int(self.line_search_steps), dtype=jnp.float32)


class TrajoptResult(NamedTuple):
    """One improvement step's outcome (all arrays; stacked over iterations by ``optimize``)."""

    actions: jax.Array
    """The new actions (T, m): improved if ``accepted``, else the input unchanged."""
    value: jax.Array
    """Return of ``actions`` (``>= old_value`` always)."""
    old_value: jax.Array
    """Return of the input actions."""
    alpha: jax.Array
    """Accepted step size (0 when not accepted)."""
    accepted: jax.Array
    """Whether a step size improved the return."""
    grad_norm: jax.Array
    """Global norm of ``dV/da`` before any clipping (NaN/inf when non-finite)."""
    nonfinite: jax.Array
    """1 when the gradient, Hessian or direction held a NaN/inf and no step was taken, else 0."""
    env_steps: jax.Array
    """Simulated steps spent: T for the differentiated rollout (its tangents or cotangents ride on
    that one pass, and it also gives ``old_value``) + T per line-search candidate."""


# --------------------------------------------------------------------------- problem builders
def env_problem(env, state) -> tuple[RolloutFn, RewardFn]:
    """``(rollout_fn, reward_fn)`` of a ``twinrl.envs.Env`` from the start ``State``.

    The state vector is ``concat(qpos, qvel)`` after each control step, simulated exactly as
    ``env.step`` does (``env.sim_step``: the task's controller, ``env.params``), and the reward is ``env.reward``,
    so ``trajectory_return`` equals ``env.unroll(state, actions)[1].sum()``. Call it inside a jit
    with the state as an argument, so one compile serves every start state.

    A ``LatencyWrapper``-ed env (an identified ``System`` with latency L) is simulated through its
    delay: step t applies the action sent at t - L, the first L from the queue in ``state.info``
    (actions sent before the window), and the reward's control term sees the sent action, clipped,
    as the wrapper's ``step`` does. So PODS/HDS optimise the actions of the system they run in;
    the last L actions of a window move no state in it, only their control cost.
    """
    nq = env.sim.nq
    data0 = state.pipeline_state
    queue = state.info[QUEUE_KEY] if isinstance(env, LatencyWrapper) else None

    def rollout_fn(actions):
        if queue is not None:
            sent = jnp.clip(actions.astype(queue.dtype), -1.0, 1.0)
            actions = jnp.concatenate([queue, sent], axis=0)[:actions.shape[0]]
        _, traj = env.sim.rollout(data0, actions, env.params, step_fn=env.sim_step)
        return jnp.concatenate([traj.qpos, traj.qvel], axis=-1)

    def reward_fn(s, a):
        if queue is not None:
            a = jnp.clip(a, -1.0, 1.0)
        return env.reward(s[:nq], s[nq:], a)[0]

    return rollout_fn, reward_fn


def _check(actions, states=None, rewards=None):
    if actions.ndim != 2:
        raise ValueError(f"actions must have shape (T, m), got {actions.shape}")
    if states is not None and (states.ndim != 2 or states.shape[0] != actions.shape[0]):
        raise ValueError(f"rollout_fn must return states of shape (T={actions.shape[0]}, n), "
                         f"got {states.shape}")
    if rewards is not None and rewards.shape != (actions.shape[0],):
        raise ValueError(f"reward_fn must return a scalar per (state, action), got shape "
                         f"{rewards.shape[1:]}")


def discounts(T: int, discount: float, dtype=jnp.float32) -> jax.Array | None:
    """``gamma^t`` for t < T, or None when ``discount == 1`` (the plain sum, bit for bit)."""
    if float(discount) == 1.0:
        return None
    return float(discount) ** jnp.arange(T, dtype=dtype)


def trajectory_return(rollout_fn: RolloutFn, reward_fn: RewardFn, actions: jax.Array,
                      discount: float = 1.0, terminal_fn: TerminalFn | None = None) -> jax.Array:
    """``V(a) = sum_t gamma^t reward_fn(s_t(a), a_t) [+ gamma^T terminal_fn(s_T(a))]``."""
    states = rollout_fn(actions)
    _check(actions, states)
    rewards = jax.vmap(reward_fn)(states, actions)
    _check(actions, states, rewards)
    w = discounts(actions.shape[0], discount, rewards.dtype)
    value = jnp.sum(rewards) if w is None else jnp.sum(w * rewards)
    if terminal_fn is not None:
        value = value + float(discount) ** actions.shape[0] * terminal_fn(states[-1])
    return value


# --------------------------------------------------------------------------- directions
def first_order_direction(rollout_fn, reward_fn, actions, discount: float = 1.0,
                          terminal_fn: TerminalFn | None = None):
    """``(V(a), dV/da, dV/da)``: the gradient is its own ascent direction (PODS Sec. 4.1)."""
    value, grad = jax.value_and_grad(
        lambda a: trajectory_return(rollout_fn, reward_fn, a, discount, terminal_fn))(actions)
    return value, grad, lambda g: g


def gauss_newton_direction(rollout_fn, reward_fn, actions, regularization: float,
                           discount: float = 1.0, terminal_fn: TerminalFn | None = None,
                           terminal_curvature: bool = False):
    """``(V(a), dV/da, solve)`` with ``solve(g) = H^-1 g``, H the damped Gauss–Newton matrix of
    ``-V`` (module docstring; PODS Sec. 4.2) over all T m actions jointly, any m.

    ``ds/da`` comes from ``jax.jacfwd`` of the rollout (T m tangents on one forward pass: cheaper
    than T n reverse passes when m < n, the usual case for robots). ``terminal_fn`` enters the
    gradient, and the matrix only if ``terminal_curvature`` (``TrajoptConfig``'s field).
    """
    T, m = actions.shape
    jac, states = jax.jacfwd(lambda a: (rollout_fn(a),) * 2, has_aux=True)(actions)
    _check(actions, states)
    n = states.shape[1]
    ds_da = jac.reshape(T, n, T * m)
    # da_t/da selects action t from the flattened sequence.
    da_da = jnp.eye(T * m, dtype=ds_da.dtype).reshape(T, m, T * m)
    Z = jnp.concatenate([ds_da, da_da], axis=1)                       # (T, n + m, T m)

    def r_z(z):
        return reward_fn(z[:n], z[n:])

    zs = jnp.concatenate([states, actions.astype(states.dtype)], axis=1)
    rewards, dr = jax.vmap(jax.value_and_grad(r_z))(zs)                # (T,), (T, n + m)
    _check(actions, states, rewards)
    d2r = jax.vmap(jax.hessian(r_z))(zs)                               # (T, n + m, n + m)
    w = discounts(T, discount, rewards.dtype)
    if w is not None:
        rewards, dr, d2r = w * rewards, w[:, None] * dr, w[:, None, None] * d2r
    if terminal_fn is not None:
        # V_term(s_T) is one more reward on the last step's state s_T = states[T - 1].
        gT = float(discount) ** T
        v_T, dv_T = jax.value_and_grad(terminal_fn)(states[-1])
        rewards = rewards.at[-1].add(gT * v_T)
        dr = dr.at[-1, :n].add(gT * dv_T)
        if terminal_curvature:
            d2r = d2r.at[-1, :n, :n].add(gT * jax.hessian(terminal_fn)(states[-1]))
    grad = jnp.einsum("tz,tzk->k", dr, Z).reshape(T, m)
    # Per-step cost curvature projected onto the PSD cone: the GN matrix is then PSD and the
    # damped system has a Cholesky factor; negative curvature of the cost is no model to trust.
    w, U = jnp.linalg.eigh(-0.5 * (d2r + jnp.swapaxes(d2r, 1, 2)))
    cost_curv = jnp.einsum("tij,tj,tkj->tik", U, jnp.maximum(w, 0.0), U)
    H = jnp.einsum("tzi,tzy,tyj->ij", Z, cost_curv, Z)
    H = H + regularization * jnp.eye(T * m, dtype=H.dtype)
    chol = jax.scipy.linalg.cho_factor(H, lower=True)
    finite_H = all_finite(H)

    def solve(g):
        d = jax.scipy.linalg.cho_solve(chol, g.reshape(T * m)).reshape(T, m)
        # A NaN Hessian poisons the direction; report it via the direction's finiteness.
        return jnp.where(finite_H, d, jnp.nan)

    return jnp.sum(rewards), grad, solve


# --------------------------------------------------------------------------- line search
def line_search(rollout_fn, reward_fn, actions, direction, old_value, config: TrajoptConfig,
                terminal_fn: TerminalFn | None = None):
    """Best strictly improving candidate among ``clip(a + alpha_k d)``; else the input.

    All K candidates are simulated in one vmapped call, so taking the best of them (rather than
    the first improving one, as sequential backtracking would) costs nothing extra.
    Returns ``(actions, value, alpha, accepted)``.
    """
    alphas = config.alphas.astype(actions.dtype)
    cands = jnp.clip(actions[None] + alphas[:, None, None] * direction[None],
                     config.action_low, config.action_high)
    values = jax.vmap(lambda a: trajectory_return(rollout_fn, reward_fn, a, config.discount,
                                                  terminal_fn))(cands)
    values = jnp.where(jnp.isfinite(values), values, -jnp.inf)
    k = jnp.argmax(values)
    accepted = values[k] > old_value
    new_actions = jnp.where(accepted, cands[k], actions)
    new_value = jnp.where(accepted, values[k], old_value)
    return new_actions, new_value, jnp.where(accepted, alphas[k], 0.0), accepted


# --------------------------------------------------------------------------- the step
def improve(rollout_fn: RolloutFn, reward_fn: RewardFn, actions: jax.Array,
            config: TrajoptConfig, terminal_fn: TerminalFn | None = None,
            direction_scale: jax.Array | float = 1.0) -> TrajoptResult:
    """One PODS improvement step of ``actions`` (T, m): direction, hygiene, line search.

    ``terminal_fn`` adds ``gamma^T V_term(s_T)`` to the objective (module docstring).
    ``direction_scale`` (may be traced) multiplies the direction, so the line search tries
    ``direction_scale * step_size * 2^-k`` (HDS anneals it; ``step_size`` is a static float);
    the reported ``alpha`` includes it. Jit it with the functions and config closed over, e.g.
    ``jax.jit(lambda s, a: improve(*env_problem(env, s), a, config))``.
    """
    if not isinstance(config, TrajoptConfig):
        raise TypeError(f"config must be a TrajoptConfig, got {type(config).__name__}")
    actions = jnp.asarray(actions)
    if not jnp.issubdtype(actions.dtype, jnp.floating):
        raise TypeError(f"actions must be floating point, got dtype {actions.dtype}")
    _check(actions)
    T = actions.shape[0]
    if config.order == 1:
        old_value, grad, solve = first_order_direction(rollout_fn, reward_fn, actions,
                                                       config.discount, terminal_fn)
    else:
        old_value, grad, solve = gauss_newton_direction(rollout_fn, reward_fn, actions,
                                                        config.regularization, config.discount,
                                                        terminal_fn, config.terminal_curvature)
    grad_norm = global_norm(grad)
    g = grad
    if config.max_grad_norm is not None:
        g = g * jnp.where(grad_norm > config.max_grad_norm,
                          config.max_grad_norm / jnp.maximum(grad_norm, 1e-30), 1.0)
    direction = solve(g)
    if config.max_step_norm is not None:
        dn = global_norm(direction)
        direction = direction * jnp.where(dn > config.max_step_norm,
                                          config.max_step_norm / jnp.maximum(dn, 1e-30), 1.0)
    ok = all_finite(direction) & jnp.isfinite(old_value)
    # where(), not multiplication: 0 * NaN is NaN.
    direction = jnp.where(ok, direction_scale * direction, 0.0)
    new_actions, value, alpha, accepted = line_search(rollout_fn, reward_fn, actions, direction,
                                                      old_value, config, terminal_fn)
    accepted = accepted & ok
    new_actions = jnp.where(accepted, new_actions, actions)
    value = jnp.where(accepted, value, old_value)
    steps = T * (1 + int(config.line_search_steps))
    return TrajoptResult(actions=new_actions, value=value, old_value=old_value,
                         alpha=jnp.where(accepted, alpha * direction_scale, 0.0),
                         accepted=accepted,
                         grad_norm=grad_norm, nonfinite=(~ok).astype(jnp.int32),
                         env_steps=jnp.asarray(steps, jnp.int32))


def optimize(rollout_fn: RolloutFn, reward_fn: RewardFn, actions: jax.Array,
             config: TrajoptConfig, iterations: int, terminal_fn: TerminalFn | None = None,
             direction_scale: jax.Array | float = 1.0) -> tuple[jax.Array, TrajoptResult]:
    """``iterations`` improvement steps in one ``lax.scan`` (arguments as ``improve``'s).

    Returns the final actions and the per-iteration ``TrajoptResult``s stacked on a leading axis
    (``history.env_steps.sum()`` is the total simulation cost).
    """
    if int(iterations) < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")

    def body(a, _):
        res = improve(rollout_fn, reward_fn, a, config, terminal_fn, direction_scale)
        return res.actions, res

    return jax.lax.scan(body, jnp.asarray(actions), None, length=int(iterations))
