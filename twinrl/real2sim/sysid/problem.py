"""The least-squares problem of sysid: robust residuals of windows rolled out through MJX.

``build_problem`` turns data and a config into a ``Problem``: normalised residuals of every window
(rolled out open loop from its recorded start state), their forward-mode Jacobian with respect to
the parameters in unconstrained coordinates (``to_unconstrained``/``from_unconstrained``:
positivity by reparameterisation), the robust loss ``rho`` (Huber, Cauchy) and the Gaussian
prior. The simulator carries a tiny friction loss on every dof whose friction loss is fitted, so
MJX keeps its constraint row (``twinrl.real2sim.sysid``, "Friction loss and MJX").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from twinrl.envs.base import Env
from twinrl.physics import PhysParams, Sim
from twinrl.physics.integrator import tangent_delta, tangent_qpos
from twinrl.physics.params import NONNEGATIVE, POSITIVE, position_servos
from twinrl.real2sim.sysid.config import SysidConfig, default_param_names, parse_param
from twinrl.real2sim.sysid.data import Windows, windows_from_dataset

__all__ = ["rho", "Problem", "build_problem", "as_f64", "param_value", "to_unconstrained",
           "from_unconstrained", "dvalue_du"]


def rho(r: np.ndarray, kind: str, c: float) -> tuple[np.ndarray, np.ndarray]:
    """Robust loss value and IRLS weight (rho'(r) / r) of normalised residuals."""
    a = np.abs(r)
    if kind == "l2":
        return 0.5 * r * r, np.ones_like(r)
    if kind == "huber":
        return (np.where(a <= c, 0.5 * r * r, c * (a - 0.5 * c)),
                np.where(a <= c, 1.0, c / np.maximum(a, c)))
    return 0.5 * c * c * np.log1p((r / c) ** 2), 1.0 / (1.0 + (r / c) ** 2)


def _rho_jnp(r, kind: str, c: float):
    a = jnp.abs(r)
    if kind == "l2":
        return 0.5 * r * r
    if kind == "huber":
        return jnp.where(a <= c, 0.5 * r * r, c * (a - 0.5 * c))
    return 0.5 * c * c * jnp.log1p((r / c) ** 2)


class Problem:
    """The sysid objective on a set of windows: residuals, Jacobians, robust loss, rollout count.

    Built by ``build_problem``; shared by ``fit`` and the CMA-ES baseline so both optimise the
    very same function in the very same (unconstrained) coordinates. ``theta`` is the vector of
    unconstrained values of ``names`` (fitted and known); ``free`` marks the fitted ones.
    """

    def __init__(self, env: Env, windows: Windows, config: SysidConfig):
        c = config
        self.env, self.windows, self.config = env, windows, c
        fitted = tuple(c.params) if c.params is not None else default_param_names(env)
        known = {str(k): float(v) for k, v in c.known}
        fitted = tuple(n for n in fitted if n not in known)  # a known value is not fitted
        self.names = fitted + tuple(known)
        if not fitted:
            raise ValueError("SysidConfig leaves no parameter to fit")
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"SysidConfig.params names a parameter twice: {self.names}")
        self.spec = [parse_param(env, n) for n in self.names]
        self.free = np.array([n not in known for n in self.names])
        self.n_free = int(self.free.sum())

        # The fitting simulator: the task's MJCF with a friction-loss row on every fitted dof.
        mj = _copy_model(env.sim.mj_model)
        for f, i in self.spec:
            if f == "frictionloss" and mj.dof_frictionloss[i] <= 0:
                mj.dof_frictionloss[i] = c.frictionloss_floor
        self.sim = env.sim.recompiled(mj)

        # Nominal: the env's parameters (identified earlier, or the MJCF's); initial: nominal
        # with near-zero non-negative fitted values lifted to nonneg_init; known: given values.
        start = env.params if env.params is not None else PhysParams.from_model(env.sim.mj_model)
        self.nominal_params = as_f64(start)
        nom = self.nominal_params.as_dict()
        self.nominal = np.array([param_value(nom, f, i) for f, i in self.spec])
        init = self.nominal.copy()
        for k, (f, i) in enumerate(self.spec):
            if self.free[k] and f in NONNEGATIVE:
                init[k] = max(init[k], c.nonneg_init)
            if not self.free[k]:
                init[k] = known[self.names[k]]
            if f in POSITIVE and init[k] <= 0 and self.free[k]:
                raise ValueError(f"parameter {self.names[k]} is 0 in the MJCF (a massless body, a "
                                 "frictionless geom or an actuator without gain): it stays 0 and "
                                 "cannot be fitted")
            if f in POSITIVE and init[k] <= 0:
                raise ValueError(f"parameter {self.names[k]} must be > 0, got {init[k]}")
        self.initial = init
        self.base_u = {k: np.asarray(v, np.float64) for k, v in
                       jax.tree_util.tree_map(np.asarray, self.nominal_params.unconstrain()).items()}
        self.theta0 = np.array([to_unconstrained(f, v) for (f, _), v in zip(self.spec, init)])

        # Per-dimension normalisation of residuals: the spread of the recorded observations.
        y = windows.targets.reshape(-1, windows.targets.shape[-1])
        self.scale = np.maximum(np.std(y, axis=0), 1e-3 * max(float(np.std(y)), 1e-12) + 1e-9)
        weights = np.ones(y.shape[-1])
        if c.observation_weights is not None:
            if len(c.observation_weights) != y.shape[-1]:
                raise ValueError(f"SysidConfig.observation_weights has "
                                 f"{len(c.observation_weights)} entries; {env.name}'s "
                                 f"observation has {y.shape[-1]}")
            weights = np.asarray(c.observation_weights, np.float64)
        n = len(windows.qpos0)
        B = int(c.batch_windows)
        self.batch = B
        self.n_windows = n
        self.n_batches = -(-n // B)
        pad = self.n_batches * B - n
        self._idx = np.concatenate([np.arange(n), np.zeros(pad, int)])
        self.mask = np.concatenate([np.ones(n), np.zeros(pad)]).reshape(self.n_batches, B)
        self.qpos0 = np.asarray(windows.qpos0, np.float64)
        self.qvel0 = np.asarray(windows.qvel0, np.float64)
        """Start state of each window: recorded, or estimated by ``fit`` (``estimate_start``)."""
        self.rollouts = 0
        """Simulated window rollouts so far (a forward pass of a window counts 1, a reverse-mode
        gradient pass 1 more, a forward-mode Jacobian 1 per tangent more)."""
        self._fns = _functions(env, self.sim, tuple(self.spec), c.window, windows.max_latency,
                               c.loss, c.loss_scale)
        self._consts = ({k: jnp.asarray(v) for k, v in self.base_u.items()},
                        jnp.asarray(np.stack([1.0 / self.scale, weights / self.scale])))

    def _batches(self, qpos0=None, qvel0=None):
        q = self.qpos0 if qpos0 is None else qpos0
        v = self.qvel0 if qvel0 is None else qvel0
        w = self.windows
        for b in range(self.n_batches):
            i = self._idx[b * self.batch:(b + 1) * self.batch]
            yield (q[i], v[i], w.actions[i], w.obs0[i], w.targets[i])

    # ------------------------------------------------------------------ evaluations
    def residuals(self, theta, latency: int, qpos0=None, qvel0=None) -> np.ndarray:
        """Normalised residuals (n_windows, W + 1, obs_size) at unconstrained ``theta``: the
        window's start observation, then its W recorded next observations. Start states default
        to ``self.qpos0/qvel0``."""
        th = jnp.asarray(theta)
        out = [np.asarray(self._fns["res"](th, latency, *self._consts, *b))
               for b in self._batches(qpos0, qvel0)]
        self.rollouts += self.n_windows
        return np.concatenate(out)[:self.n_windows]

    def jacobian(self, theta, latency: int, start: bool = False):
        """Residuals and Jacobians w.r.t. ``theta`` (n, W+1, o, P) and, with ``start``, w.r.t.
        each window's own start state in tangent coordinates (n, W+1, o, 2 nv: ``retract``)."""
        th = jnp.asarray(theta)
        rs, js, jx = [], [], []
        fn = self._fns["jac_x" if start else "jac"]  # jitted lazily: only what is used compiles
        for b in self._batches():
            out = fn(th, latency, *self._consts, *b)
            rs.append(np.asarray(out[0]))
            js.append(np.asarray(out[1]))
            if start:
                jx.append(np.concatenate([np.asarray(out[2]), np.asarray(out[3])], -1))
        n = self.n_windows
        self.rollouts += n * (1 + self.n_free + (2 * self.sim.nv if start else 0))
        r, J = np.concatenate(rs)[:n], np.concatenate(js)[:n]
        return (r, J, np.concatenate(jx)[:n]) if start else (r, J)

    def retract(self, qpos0: np.ndarray, dq: np.ndarray) -> np.ndarray:
        """Window start positions ``qpos0`` (n, nq) moved by tangent steps ``dq`` (n, nv)."""
        return np.asarray(self._fns["retract"](jnp.asarray(qpos0), jnp.asarray(dq)), np.float64)

    def start_offset(self, qpos0=None, qvel0=None) -> np.ndarray:
        """Each window's start state (default: the current estimate) less its recorded one, in
        tangent coordinates (n, 2 nv): what the start states' prior weighs."""
        q = self.qpos0 if qpos0 is None else qpos0
        v = self.qvel0 if qvel0 is None else qvel0
        dq = np.asarray(self._fns["delta"](jnp.asarray(self.windows.qpos0, jnp.float64),
                                           jnp.asarray(q, jnp.float64)), np.float64)
        return np.concatenate([dq, v - np.asarray(self.windows.qvel0, np.float64)], -1)

    def loss_and_grad(self, theta, latency: int) -> tuple[float, np.ndarray]:
        """Sum of the robust loss over all residuals, and its gradient (reverse mode)."""
        th = jnp.asarray(theta)
        tot, g = 0.0, np.zeros(len(self.names))
        for b, m in zip(self._batches(), self.mask):
            v, gb = self._fns["grad"](th, latency, *self._consts, jnp.asarray(m), *b)
            tot += float(v)
            g += np.asarray(gb)
        self.rollouts += 2 * self.n_windows
        return tot, g

    def data_loss(self, r: np.ndarray) -> float:
        return float(np.sum(rho(r, self.config.loss, self.config.loss_scale)[0]))

    def prior(self, theta) -> float:
        d = (np.asarray(theta) - self.theta0)[self.free] / self.config.prior_sd
        return 0.5 * float(d @ d)

    def loss(self, theta, latency: int) -> float:
        """Mean robust loss per residual (what the report and the baselines compare)."""
        r = self.residuals(theta, latency)
        return self.data_loss(r) / r.size

    def params_of(self, theta) -> PhysParams:
        p = self._fns["params"](jnp.asarray(theta), self._consts[0])
        return as_f64(jax.tree_util.tree_map(np.asarray, p))

    def values_of(self, theta) -> np.ndarray:
        """Physical values of ``names`` at unconstrained ``theta``."""
        return np.array([from_unconstrained(f, t)
                         for (f, _), t in zip(self.spec, np.asarray(theta))])


_FUNCTIONS: dict = {}


def _functions(env: Env, sim: Sim, spec: tuple, W: int, L: int, kind: str, cs: float) -> dict:
    """The jitted residual / Jacobian / gradient functions, built once per problem structure.

    Everything that varies between datasets (the nominal parameters, the normalisation, the
    windows) is an argument, so fits of the same task reuse one compilation (cold compiles of the
    forward-mode Jacobian through MJX take tens of seconds)."""
    key = (type(env), env.sim.name, env.sim.frame_skip, env.config,
           tuple(np.asarray(sim.mj_model.dof_frictionloss).tolist()), spec, W, L, kind, cs,
           bool(jax.config.jax_enable_x64))
    if key in _FUNCTIONS:
        return _FUNCTIONS[key]

    servo = position_servos(sim.mj_model)

    def to_params(theta, base_u):
        u = dict(base_u)
        for j, (f, i) in enumerate(spec):
            u[f] = u[f].at[i].set(theta[j])
            if f == "gain" and servo[i]:  # a position servo's stiffness: gain and bias together
                u["bias"] = u["bias"].at[i, 1].set(-jnp.exp(theta[j]))
        return PhysParams.constrain(u)

    def window(theta, latency, base_u, inv_scale, q, v, a, y0, y):
        p = to_params(theta, base_u)
        template = sim.init()
        a = jax.lax.dynamic_slice_in_dim(a, L - latency, W, 0)
        d = template.replace(qpos=q.astype(template.qpos.dtype),
                             qvel=v.astype(template.qvel.dtype))
        # the task's controller, on this window's simulator (which may carry friction rows)
        _, tr = sim.rollout(d, a, p, step_fn=lambda d, a, p: sim.step(
            d, env.control(d.qpos, d.qvel, a), p))
        qs = jnp.concatenate([d.qpos[None], tr.qpos])
        vs = jnp.concatenate([d.qvel[None], tr.qvel])
        pred = jax.vmap(env.observe)(qs, vs).astype(q.dtype)
        # inv_scale: row 0 for the window's start, row 1 (observation_weights applied) for the
        # steps after it. The recorded start keeps every dimension, so each start state stays
        # pinned where it was recorded even in dimensions the weights leave out.
        err = pred - jnp.concatenate([y0[None], y])
        return jnp.concatenate([err[:1] * inv_scale[0], err[1:] * inv_scale[1]])

    batched = jax.vmap(window, in_axes=(None, None, None, None, 0, 0, 0, 0, 0))

    def jac_theta(theta, latency, base_u, inv_scale, *rest):
        f = lambda th: window(th, latency, base_u, inv_scale, *rest)
        return f(theta), jax.jacfwd(f)(theta)

    jnt_types = tuple(int(t) for t in sim.mj_model.jnt_type)

    def jac_all(theta, latency, base_u, inv_scale, q, v, *rest):
        # the start state's Jacobian in tangent coordinates (``tangent_qpos``): a quaternion's
        # norm is no direction to estimate (its Hessian is zero there, and so was LM's damping)
        f = lambda th, dq, vv: window(th, latency, base_u, inv_scale,
                                      tangent_qpos(jnt_types, q, dq), vv, *rest)
        Jt, Jq, Jv = jax.jacfwd(f, argnums=(0, 1, 2))(theta, jnp.zeros_like(v), v)
        return f(theta, jnp.zeros_like(v), v), Jt, Jq, Jv

    ax = (None, None, None, None, 0, 0, 0, 0, 0)

    def batch_loss(theta, latency, base_u, inv_scale, mask, *args):
        r = batched(theta, latency, base_u, inv_scale, *args)
        return jnp.sum(_rho_jnp(r, kind, cs) * mask[:, None, None])

    fns = dict(
        params=jax.jit(to_params),
        res=jax.jit(batched),
        jac=jax.jit(jax.vmap(jac_theta, in_axes=ax)),
        jac_x=jax.jit(jax.vmap(jac_all, in_axes=ax)),
        grad=jax.jit(jax.value_and_grad(batch_loss)),
        retract=jax.jit(jax.vmap(lambda q, dq: tangent_qpos(jnt_types, q, dq))),
        delta=jax.jit(jax.vmap(lambda q0, q1: tangent_delta(jnt_types, q0, q1))),
    )
    _FUNCTIONS[key] = fns
    return fns


def build_problem(env: Env, data, config: SysidConfig | None = None) -> Problem:
    """The sysid objective of ``config`` on ``data`` (a Dataset, arrays or ``Windows``)."""
    config = config or SysidConfig()
    with jax.enable_x64(bool(config.float64)):
        w = data if isinstance(data, Windows) else windows_from_dataset(
            env, data, config.window, config.stride, config.max_latency)
        if w.max_latency < config.max_latency or w.targets.shape[1] != config.window:
            raise ValueError(f"windows were cut for window={w.targets.shape[1]}, max_latency="
                             f"{w.max_latency}; the config asks {config.window}, "
                             f"{config.max_latency}")
        if config.max_windows is not None and len(w.qpos0) > config.max_windows:
            keep = np.linspace(0, len(w.qpos0) - 1, int(config.max_windows)).round().astype(int)
            w = w.select(keep)
        return Problem(env, w, config)


def _copy_model(m: mujoco.MjModel) -> mujoco.MjModel:
    import copy
    return copy.deepcopy(m)


def as_f64(p: PhysParams) -> PhysParams:
    return PhysParams(**{k: np.asarray(v, np.float64) for k, v in p.as_dict().items()})


def param_value(d, f, i) -> float:
    return float(np.asarray(d[f]).reshape(-1)[i])


def to_unconstrained(field: str, v: float) -> float:
    if field in POSITIVE:
        return float(np.log(v))
    if field in NONNEGATIVE:
        v = max(float(v), 1e-9)
        return float(v + np.log(-np.expm1(-v)))
    return float(v)


def from_unconstrained(field: str, u: float) -> float:
    if field in POSITIVE:
        return float(np.exp(u))
    if field in NONNEGATIVE:
        return float(np.logaddexp(0.0, u))
    return float(u)


def dvalue_du(field: str, u: float) -> float:
    if field in POSITIVE:
        return float(np.exp(u))
    if field in NONNEGATIVE:
        return float(1.0 / (1.0 + np.exp(-u)))
    return 1.0
