"""System identification from trajectories: fit ``PhysParams`` and the action latency to a dataset.

Real2Sim, first half (ARCHITECTURE.md, "The loop, as data"; SAM-RL Sec. 4.1, the Hybrid
Differentiable Simulation study's "parameter identification"): find the simulator parameters under
which recorded real transitions are most likely, by gradient-based optimisation *through* the
simulator.

Method
------
* **Multiple shooting** (Bock & Plitt 1984). A long rollout from one recorded state diverges (a
  pole swinging through upright amplifies any parameter error exponentially, and its gradient
  explodes with it), so the data are cut into short windows of ``window`` steps; each window
  starts from the state read off its first recorded observation (``Env.state_from_obs``), is
  rolled out open loop with its recorded actions, and is compared with the recorded next
  observations. Windows are independent, so they are vmapped, in fixed-size batches (one compile
  for any dataset size).
* **Robust loss** on residuals normalised per observation dimension (by the data's spread):
  Huber or Cauchy, so a few bad windows (a glitch, an unmodelled knock) cannot drag the fit.
* **Bounds by reparameterisation**: the optimiser works on ``PhysParams.unconstrain()``
  coordinates (log for masses and gains, softplus^-1 for damping and friction), so every step is
  a valid model. A weak Gaussian prior around the initial values (``prior_sd`` in these
  coordinates) only matters along directions the data cannot see.
* **Parameters at their bound 0**: softplus coordinates cannot reach 0 (the value's slope
  vanishes there), so a damping or friction loss whose truth is 0 would stall at a small positive
  value and bias the parameters that trade off against it. After the fit, each fitted
  non-negative parameter is refitted held at 0 and kept there when the data's deviance rises by
  less than ``bound_lr`` (a likelihood-ratio test against the boundary null, scaled for the
  correlation inside a window); it is reported ``at bound 0`` with a one-sided sd in physical
  units, and the other parameters' sd are marginal over it.
* **Levenberg-Marquardt** (Gauss-Newton with Marquardt damping, iteratively reweighted for the
  robust loss) on the residual Jacobian from forward-mode AD (one tangent per parameter through
  every window); ``optimizer="adam"`` uses optax's Adam on reverse-mode gradients instead (kept
  to measure: LM needs far fewer rollouts on these few-parameter problems).
* **Latency** is discrete: the fit is run for each latency 0..``max_latency`` (the action applied
  at step t is the one sent at t - latency; zeros before the episode began, as the real twin
  does) and the latency with the smallest loss is kept.
* **Uncertainty** by the Laplace / Gauss-Newton approximation: the Fisher information
  ``J^T W J / sigma_d^2`` of the residuals at the optimum (``sigma_d^2`` the residual variance of
  each observation dimension), inverted with the prior. Residuals inside one window are
  correlated (one noisy start state moves all of them), so by default the covariance is the
  window-clustered sandwich ``H^-1 (sum_w g_w g_w^T) H^-1`` (``uncertainty="sandwich"``), which
  stays honest under that correlation and under model mismatch; ``"gauss_newton"`` is the plain
  ``H^-1``.
* **Identifiability**: eigen-directions of the data's Fisher information whose standard deviation
  exceeds ``max_rel_sd`` are *flat*. A parameter whose posterior sd exceeds ``max_rel_sd`` is
  reported not identifiable. If a direction is all but unconstrained (sd > ``flat_sd``) and
  mostly one parameter (e.g. a geom friction without contacts), that parameter is put back to its
  nominal value and the rest are refitted;
  if it is a combination (rigid-body dynamics are unchanged when every mass, force gain, damping
  and friction is scaled by one factor -- trajectories alone cannot tell a heavy robot with a
  strong motor from a light one with a weak motor), its component stays at the prior and the
  parameters in it are flagged "only in combination". Fix the scale with a known value
  (``SysidConfig.known``, e.g. the weighed cart mass) to identify each parameter on its own.

Friction loss and MJX: MJX allocates a friction-loss constraint row only for dofs whose friction
loss is non-zero in the compiled MJCF (``dof_hasfrictionloss``, fixed at ``mjx.put_model``); on
other dofs ``PhysParams.frictionloss`` has no effect and zero gradient. The cartpole's MJCF has
no rail friction, its real twin does. So the fit builds its own simulator from the MJCF with a
tiny friction loss (``frictionloss_floor``, 1e-6 N: no measurable force) on every dof whose
friction loss is fitted: the row exists, and the fitted value flows into it.

The evaluation against the truth (``compare_to_truth``) takes the true parameters as an argument
and lives apart from the fit: learning code never sees the real twin's hidden perturbation.

Example::

    twin = twinrl.real.make_real("cartpole_swingup", seed=0)
    data = collect(twin, episodes=5, seed=0)          # excitation actions on the real twin
    result = fit(twinrl.envs.make("cartpole_swingup"), data, SysidConfig())
    print_result(result)
    env = twinrl.envs.make("cartpole_swingup", system=result.system)  # params + latency
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable, Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import optax
from mujoco import mjx

from twinrl.envs.base import Env
from twinrl.envs.registry import TASKS
from twinrl.envs.system import System
from twinrl.physics import PhysParams, Sim
from twinrl.physics.params import NONNEGATIVE, POSITIVE

__all__ = [
    "SysidConfig", "SysidResult", "Windows", "Problem", "fit", "windows_from_dataset",
    "build_problem", "param_names", "compare_to_truth", "excitation_actions", "collect",
    "print_result", "FITTABLE",
]

FITTABLE = ("mass", "damping", "armature", "frictionloss", "friction", "gain", "gravity")
"""``PhysParams`` fields sysid can fit, by element name ``"field/element"``."""
DEFAULT_FIELDS = ("mass", "damping", "frictionloss", "gain")
LOSSES = ("huber", "cauchy", "l2")
OPTIMIZERS = ("lm", "adam", "adam+lm")
UNCERTAINTIES = ("sandwich", "gauss_newton")


# ---------------------------------------------------------------------------------- config
@dataclasses.dataclass(frozen=True)
class SysidConfig:
    """How ``fit`` identifies parameters. Every field has a default that works on the cartpole."""

    window: int = 20
    """Steps per shooting window (short: long open-loop rollouts diverge and their gradients
    explode; long enough that damping and friction act measurably: on the default cartpole twin,
    5 episodes, 20 steps pin the rail damping to 0.6-1.8 % sd where 10 left 1.0-2.3 % (seeds
    0-2): each window's estimated start velocity absorbs less of the dissipation)."""
    stride: int | None = None
    """Steps between window starts (default: ``window``, non-overlapping windows)."""
    params: tuple[str, ...] | None = None
    """Parameters to fit as ``"field/element"`` names (``param_names`` lists them), e.g.
    ``("mass/cart", "gain/push")``. Default: every body's mass, every dof's damping and
    friction loss, every actuator's gain."""
    known: tuple[tuple[str, float], ...] = ()
    """``(name, value)`` pairs held fixed at a value known from elsewhere (e.g. a weighed mass);
    one known mass fixes the otherwise unidentifiable overall scale."""
    max_latency: int = 1
    """Largest action latency (control steps) tried; each of 0..max_latency is fitted."""
    latency: int | None = None
    """Fit only this latency (known from elsewhere) instead of trying 0..max_latency."""
    float64: bool = True
    """Run the fit in float64 (recommended: float32 residual Jacobians are noisy)."""
    loss: str = "huber"
    """Robust loss on normalised residuals: ``huber``, ``cauchy`` or ``l2``."""
    loss_scale: float = 0.05
    """Huber/Cauchy scale, in units of each observation dimension's spread in the data."""
    estimate_start: bool = True
    """Estimate each window's start state with the parameters (full multiple shooting) instead
    of taking it from the noisy recorded observation: removes the errors-in-variables bias that
    observation noise on the start state puts on the parameters."""
    optimizer: str = "lm"
    """``lm`` (Levenberg-Marquardt), ``adam`` (optax, reverse-mode gradients), ``adam+lm``."""
    lm_steps: int = 40
    """Maximum Levenberg-Marquardt iterations per latency."""
    lm_damping: float = 1e-3
    """Initial Marquardt damping (relative to the diagonal of J^T W J)."""
    adam_steps: int = 300
    """Adam steps per latency (``optimizer`` ``adam`` or ``adam+lm``)."""
    adam_lr: float = 0.03
    """Adam learning rate in unconstrained coordinates (about a relative change per step)."""
    tol: float = 1e-6
    """Stop when an accepted step lowers the objective by less than this fraction..."""
    step_tol: float = 1e-4
    """... or moves no parameter by more than this (unconstrained units, about relative)."""
    prior_sd: float = 3.0
    """Sd of the Gaussian prior around the initial values, in unconstrained coordinates (about
    relative: 3 = a factor e^3); decides only directions the data leave flat."""
    nonneg_init: float = 0.1
    """Fitted damping / friction loss / armature whose initial value is below this start here
    (softplus coordinates have no gradient near zero)."""
    frictionloss_floor: float = 1e-6
    """Friction loss compiled into the fitting simulator on fitted dofs, so MJX has the row."""
    max_rel_sd: float = 0.1
    """A parameter (or eigen-direction) whose sd in unconstrained coordinates (about relative)
    exceeds this is not identifiable."""
    flat_sd: float = 1.0
    """An eigen-direction whose sd exceeds this (the data say next to nothing: a factor e) and
    that is mostly one parameter puts that parameter back to its nominal value."""
    uncertainty: str = "sandwich"
    """``sandwich`` (window-clustered, robust to correlated residuals) or ``gauss_newton``."""
    bound_lr: float = 2.71
    """A fitted damping / friction loss / armature is held at its bound 0 when refitting without
    it raises the data's deviance (-2 log-likelihood, made robust to the correlation inside a
    window) by less than this: 2.71 is the 5 % level of the boundary null 0.5 chi2_0 + 0.5 chi2_1.
    0 disables the test."""
    batch_windows: int = 64
    """Windows per vmapped batch (fixed, so one compile serves every dataset size)."""
    max_windows: int | None = None
    """Use at most this many windows (evenly spread); default all."""

    def __post_init__(self):
        def need(ok, what):
            if not ok:
                raise ValueError(f"SysidConfig: {what}")
        need(int(self.window) >= 1, f"window must be >= 1, got {self.window}")
        need(self.stride is None or int(self.stride) >= 1, f"stride must be >= 1, got {self.stride}")
        need(int(self.max_latency) >= 0, f"max_latency must be >= 0, got {self.max_latency}")
        need(self.latency is None or 0 <= int(self.latency) <= int(self.max_latency),
             f"latency must be in 0..max_latency={self.max_latency}, got {self.latency}")
        need(self.loss in LOSSES, f"loss must be one of {LOSSES}, got {self.loss!r}")
        need(self.optimizer in OPTIMIZERS,
             f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        need(self.uncertainty in UNCERTAINTIES,
             f"uncertainty must be one of {UNCERTAINTIES}, got {self.uncertainty!r}")
        for name in ("loss_scale", "prior_sd", "flat_sd", "nonneg_init", "frictionloss_floor", "max_rel_sd",
                     "adam_lr", "lm_damping"):
            v = getattr(self, name)
            need(math.isfinite(v) and v > 0, f"{name} must be finite and > 0, got {v}")
        need(math.isfinite(self.bound_lr) and self.bound_lr >= 0,
             f"bound_lr must be finite and >= 0, got {self.bound_lr}")
        need(int(self.batch_windows) >= 1, f"batch_windows must be >= 1, got {self.batch_windows}")
        need(self.max_windows is None or int(self.max_windows) >= 1,
             f"max_windows must be >= 1, got {self.max_windows}")
        for item in self.known:
            need(len(item) == 2 and math.isfinite(float(item[1])),
                 f"known entries are (name, finite value) pairs, got {item!r}")


# ---------------------------------------------------------------------------------- names
def _element_names(m: mujoco.MjModel, field: str) -> list[str]:
    def nm(obj, i):
        return mujoco.mj_id2name(m, obj, i) or str(i)
    if field == "mass":
        return [nm(mujoco.mjtObj.mjOBJ_BODY, i) for i in range(1, m.nbody)]
    if field in ("damping", "armature", "frictionloss"):
        out = []
        for i in range(m.nv):
            j = int(m.dof_jntid[i])
            n = nm(mujoco.mjtObj.mjOBJ_JOINT, j)
            ndof = int((m.dof_jntid == j).sum())
            out.append(n if ndof == 1 else f"{n}:{i - int(m.jnt_dofadr[j])}")
        return out
    if field == "friction":
        return [nm(mujoco.mjtObj.mjOBJ_GEOM, i) for i in range(m.ngeom)]
    if field == "gain":
        return [nm(mujoco.mjtObj.mjOBJ_ACTUATOR, i) for i in range(m.nu)]
    if field == "gravity":
        return ["x", "y", "z"]
    raise ValueError(f"field {field!r} cannot be fitted; fittable fields: {', '.join(FITTABLE)}")


def param_names(env: Env, fields: Sequence[str] = FITTABLE) -> tuple[str, ...]:
    """Every ``"field/element"`` name of ``fields`` in ``env``'s model, e.g. ``"mass/cart"``."""
    m = env.sim.mj_model
    return tuple(f"{f}/{e}" for f in fields for e in _element_names(m, f))


def _default_params(env: Env) -> tuple[str, ...]:
    m = env.sim.mj_model
    names = [f"mass/{e}" for e, w in zip(_element_names(m, "mass"), m.body_mass[1:]) if w > 0]
    return tuple(names) + param_names(env, ("damping", "frictionloss", "gain"))


def _parse(env: Env, name: str) -> tuple[str, int]:
    field, _, element = str(name).partition("/")
    if field not in FITTABLE:
        raise ValueError(f"parameter {name!r}: field {field!r} cannot be fitted; fittable "
                         f"fields: {', '.join(FITTABLE)}")
    elements = _element_names(env.sim.mj_model, field)
    if element not in elements:
        raise ValueError(f"parameter {name!r}: {env.sim.name} has no {field} element "
                         f"{element!r}; allowed: {', '.join(f'{field}/{e}' for e in elements)}")
    return field, elements.index(element)


# ---------------------------------------------------------------------------------- excitation
def excitation_actions(rng: np.random.Generator | int, T: int, m: int, *,
                       hold: tuple[int, int] = (3, 15), amplitude: float = 1.0) -> np.ndarray:
    """Random actions with persistence: levels uniform in [-amplitude, amplitude], each held for
    a random number of steps in ``hold`` (inclusive). Shape (T, m), float32.

    Persistence excites a mechanical system far better than i.i.d. noise, whose high frequencies
    the inertia filters out: held forces build up the velocities that make damping and friction
    visible, and their switches make the mass and gain visible. The safe initial policy of the
    loop's round 0.
    """
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    lo, hi = int(hold[0]), int(hold[1])
    if T < 0 or m < 1 or not 1 <= lo <= hi:
        raise ValueError(f"excitation_actions needs T >= 0, m >= 1, 1 <= hold[0] <= hold[1]; "
                         f"got T={T}, m={m}, hold={hold}")
    out = np.empty((T, m), np.float32)
    for j in range(m):
        t = 0
        while t < T:
            n = int(rng.integers(lo, hi + 1))
            out[t:t + n, j] = rng.uniform(-amplitude, amplitude)
            t += n
    return out


def collect(twin, episodes: int, seed: int = 0, *, steps: int | None = None,
            writer=None, **excitation) -> dict[str, np.ndarray]:
    """Run ``excitation_actions`` open loop on a real twin (a gymnasium env) for ``episodes``.

    Returns ``{"obs", "action", "next_obs", "reward"}`` with shapes (E, T, ...); if ``writer``
    (a ``twinrl.real.dataset.DatasetWriter``) is given, every transition is also recorded there.
    """
    rng = np.random.default_rng(seed)
    T = int(steps or twin.task.episode_length)
    m = int(twin.action_space.shape[0])
    out = {k: [] for k in ("obs", "action", "next_obs", "reward")}
    for ep in range(int(episodes)):
        acts = excitation_actions(rng, T, m, **excitation)
        obs, _ = twin.reset(seed=int(seed) * 1000 + ep)
        rows = {k: [] for k in out}
        for t, a in enumerate(acts):
            nxt, r, term, trunc, _ = twin.step(a)
            if writer is not None:
                writer.add(obs, a, r, nxt, term, trunc or t == T - 1)
            for k, v in zip(out, (obs, a, nxt, r)):
                rows[k].append(v)
            obs = nxt
            if term:
                break
        for k in out:
            out[k].append(np.asarray(rows[k]))
    lengths = {len(x) for x in out["reward"]}
    if len(lengths) != 1:  # an episode terminated early (diverged): keep ragged as a list
        return {k: list(v) for k, v in out.items()}
    return {k: np.stack(v) for k, v in out.items()}


# ---------------------------------------------------------------------------------- data
class Windows(NamedTuple):
    """Shooting windows cut from recorded episodes (n windows of W steps)."""

    qpos0: np.ndarray
    """(n, nq) state each window starts from (``Env.state_from_obs`` of its first obs)."""
    qvel0: np.ndarray
    """(n, nv)."""
    actions: np.ndarray
    """(n, max_latency + W, nu) actions sent at steps t0 - max_latency .. t0 + W - 1 (zeros
    before the episode began)."""
    obs0: np.ndarray
    """(n, obs_size) recorded observation at each window's start."""
    targets: np.ndarray
    """(n, W, obs_size) recorded next observations."""
    episode: np.ndarray
    """(n,) index of the episode (in the order given) each window comes from."""
    start: np.ndarray
    """(n,) step within the episode at which each window starts."""
    max_latency: int


def _episodes_of(data) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """``(label, obs, action, next_obs)`` per episode from a Dataset, a mapping or a list."""
    if hasattr(data, "episodes") and hasattr(data, "episode_starts"):  # twinrl.real.dataset
        out = []
        for ep in data.episodes():
            step = np.asarray(ep.step)
            if len(step) and not np.array_equal(step, np.arange(step[0], step[0] + len(step))):
                gap = int(np.flatnonzero(np.diff(step) != 1)[0])
                raise ValueError(f"episode {ep.id}: steps are not contiguous (step {step[gap]} is "
                                 f"followed by {step[gap + 1]}): records were lost there")
            out.append((f"episode {ep.id}", ep.obs, ep.action, ep.next_obs))
        return out
    if isinstance(data, Mapping):
        missing = [k for k in ("obs", "action", "next_obs") if k not in data]
        if missing:
            raise ValueError(f"data is missing {', '.join(missing)}; give obs, action, next_obs "
                             "arrays (T, dim) or (episodes, T, dim), or a twinrl Dataset")
        obs, act, nxt = data["obs"], data["action"], data["next_obs"]
        if isinstance(obs, (list, tuple)):
            return [(f"episode {i}", o, a, n) for i, (o, a, n) in enumerate(zip(obs, act, nxt))]
        obs, act, nxt = np.asarray(obs), np.asarray(act), np.asarray(nxt)
        if obs.ndim == 3:
            if not (act.ndim == 3 and nxt.ndim == 3):
                raise ValueError(f"data: obs is (episodes, T, dim) {obs.shape} but action is "
                                 f"{act.shape} and next_obs {nxt.shape}")
            return [(f"episode {i}", obs[i], act[i], nxt[i]) for i in range(obs.shape[0])]
        return [("episode 0", obs, act, nxt)]
    if isinstance(data, (list, tuple)):
        return [(f"episode {i}", e["obs"], e["action"], e["next_obs"]) for i, e in enumerate(data)]
    raise TypeError(f"data must be a twinrl.real.dataset.Dataset, a mapping of arrays or a list "
                    f"of episodes, got {type(data).__name__}")


def windows_from_dataset(env: Env, data, window: int, stride: int | None = None,
                         max_latency: int = 0) -> Windows:
    """Cut every episode of ``data`` into shooting windows of ``window`` steps.

    ``data``: a ``twinrl.real.dataset.Dataset`` (e.g. ``twinrl.real.dataset.read(path)``), a
    mapping with ``obs``, ``action``, ``next_obs`` arrays of shape (T, dim) or (E, T, dim) (or
    lists of per-episode arrays), or a list of such per-episode mappings.
    Raises ``ValueError`` naming the episode and step of a NaN/inf, a dimension that does not
    match ``env``, or an episode shorter than ``window``.
    """
    window, stride = int(window), int(stride or window)
    if window < 1 or stride < 1:
        raise ValueError(f"window and stride must be >= 1, got {window}, {stride}")
    meta_env = getattr(data, "meta", {}).get("env") if hasattr(data, "meta") else None
    if meta_env and meta_env != env.name:
        from twinrl.envs import TASKS
        if meta_env not in TASKS or TASKS[meta_env].env_class.scene != env.scene:
            raise ValueError(f"the dataset was recorded on {meta_env!r}, a different system "
                             f"from {env.name!r} (scene {env.scene!r})")
    o_dim, a_dim = env.observation_size, env.action_size
    episodes = _episodes_of(data)
    if not episodes:
        raise ValueError("data holds no episodes")
    to_state = jax.jit(env.state_from_obs)
    cols = {k: [] for k in Windows._fields if k != "max_latency"}
    for i, (label, obs, act, nxt) in enumerate(episodes):
        obs, act, nxt = (np.asarray(x, np.float64) for x in (obs, act, nxt))
        if act.ndim == 1 and a_dim == 1:
            act = act[:, None]
        for nm, x, d in (("obs", obs, o_dim), ("action", act, a_dim), ("next_obs", nxt, o_dim)):
            if x.ndim != 2 or x.shape[1] != d:
                raise ValueError(f"{label}: {nm} has shape {x.shape}; {env.name} needs (T, {d})")
        if not (len(obs) == len(act) == len(nxt)):
            raise ValueError(f"{label}: obs, action and next_obs have different lengths "
                             f"{len(obs)}, {len(act)}, {len(nxt)}")
        for nm, x in (("obs", obs), ("action", act), ("next_obs", nxt)):
            bad = ~np.isfinite(x)
            if bad.any():
                t, j = (int(v) for v in np.argwhere(bad)[0])
                raise ValueError(f"{label}: {nm}[{t}, {j}] is {x[t, j]} (NaN/inf); drop or "
                                 "repair that step before sysid")
        T = len(obs)
        if T < window:
            raise ValueError(f"{label} has {T} steps, shorter than the shooting window of "
                             f"{window}; use a shorter window or drop the episode")
        starts = np.arange(0, T - window + 1, stride)
        qpos, qvel = (np.asarray(x, np.float64) for x in to_state(obs[starts]))
        padded = np.concatenate([np.zeros((max_latency, a_dim)), act])
        cols["qpos0"].append(qpos)
        cols["qvel0"].append(qvel)
        cols["actions"].append(np.stack([padded[s:s + max_latency + window] for s in starts]))
        cols["obs0"].append(obs[starts])
        cols["targets"].append(np.stack([nxt[s:s + window] for s in starts]))
        cols["episode"].append(np.full(len(starts), i))
        cols["start"].append(starts)
    return Windows(**{k: np.concatenate(v) for k, v in cols.items()},
                   max_latency=int(max_latency))


# ---------------------------------------------------------------------------------- problem
def _rho(r: np.ndarray, kind: str, c: float) -> tuple[np.ndarray, np.ndarray]:
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
        fitted = tuple(c.params) if c.params is not None else _default_params(env)
        known = {str(k): float(v) for k, v in c.known}
        fitted = tuple(n for n in fitted if n not in known)  # a known value is not fitted
        self.names = fitted + tuple(known)
        if not fitted:
            raise ValueError("SysidConfig leaves no parameter to fit")
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"SysidConfig.params names a parameter twice: {self.names}")
        self.spec = [_parse(env, n) for n in self.names]
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
        self.nominal_params = _as_f64(start)
        nom = self.nominal_params.as_dict()
        self.nominal = np.array([_get(nom, f, i) for f, i in self.spec])
        init = self.nominal.copy()
        for k, (f, i) in enumerate(self.spec):
            if self.free[k] and f in NONNEGATIVE:
                init[k] = max(init[k], c.nonneg_init)
            if not self.free[k]:
                init[k] = known[self.names[k]]
            if f in POSITIVE and init[k] <= 0:
                raise ValueError(f"parameter {self.names[k]} must be > 0, got {init[k]}")
        self.initial = init
        self.base_u = {k: np.asarray(v, np.float64) for k, v in
                       jax.tree_util.tree_map(np.asarray, self.nominal_params.unconstrain()).items()}
        self.theta0 = np.array([_to_u(f, v) for (f, _), v in zip(self.spec, init)])

        # Per-dimension normalisation of residuals: the spread of the recorded observations.
        y = windows.targets.reshape(-1, windows.targets.shape[-1])
        self.scale = np.maximum(np.std(y, axis=0), 1e-3 * max(float(np.std(y)), 1e-12) + 1e-9)
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
                        jnp.asarray(1.0 / self.scale))

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
        each window's own start state (n, W+1, o, nq + nv)."""
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
        self.rollouts += n * (1 + self.n_free + (self.sim.nq + self.sim.nv if start else 0))
        r, J = np.concatenate(rs)[:n], np.concatenate(js)[:n]
        return (r, J, np.concatenate(jx)[:n]) if start else (r, J)

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
        return float(np.sum(_rho(r, self.config.loss, self.config.loss_scale)[0]))

    def prior(self, theta) -> float:
        d = (np.asarray(theta) - self.theta0)[self.free] / self.config.prior_sd
        return 0.5 * float(d @ d)

    def loss(self, theta, latency: int) -> float:
        """Mean robust loss per residual (what the report and the baselines compare)."""
        r = self.residuals(theta, latency)
        return self.data_loss(r) / r.size

    def params_of(self, theta) -> PhysParams:
        p = self._fns["params"](jnp.asarray(theta), self._consts[0])
        return _as_f64(jax.tree_util.tree_map(np.asarray, p))

    def values_of(self, theta) -> np.ndarray:
        """Physical values of ``names`` at unconstrained ``theta``."""
        return np.array([_from_u(f, t) for (f, _), t in zip(self.spec, np.asarray(theta))])

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

    def to_params(theta, base_u):
        u = dict(base_u)
        for j, (f, i) in enumerate(spec):
            u[f] = u[f].at[i].set(theta[j])
        return PhysParams.constrain(u)

    def window(theta, latency, base_u, inv_scale, q, v, a, y0, y):
        p = to_params(theta, base_u)
        template = sim.init()
        a = jax.lax.dynamic_slice_in_dim(a, L - latency, W, 0)
        ctrl = jax.vmap(env.action_to_ctrl)(a)
        d = template.replace(qpos=q.astype(template.qpos.dtype),
                             qvel=v.astype(template.qvel.dtype))
        _, tr = sim.rollout(d, ctrl, p)
        qs = jnp.concatenate([d.qpos[None], tr.qpos])
        vs = jnp.concatenate([d.qvel[None], tr.qvel])
        pred = jax.vmap(env.observe)(qs, vs).astype(q.dtype)
        return (pred - jnp.concatenate([y0[None], y])) * inv_scale

    batched = jax.vmap(window, in_axes=(None, None, None, None, 0, 0, 0, 0, 0))

    def jac_theta(theta, latency, base_u, inv_scale, *rest):
        f = lambda th: window(th, latency, base_u, inv_scale, *rest)
        return f(theta), jax.jacfwd(f)(theta)

    def jac_all(theta, latency, base_u, inv_scale, q, v, *rest):
        f = lambda th, qq, vv: window(th, latency, base_u, inv_scale, qq, vv, *rest)
        Jt, Jq, Jv = jax.jacfwd(f, argnums=(0, 1, 2))(theta, q, v)
        return f(theta, q, v), Jt, Jq, Jv

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
            w = Windows(*(getattr(w, k)[keep] for k in Windows._fields[:-1]), w.max_latency)
        return Problem(env, w, config)


def _copy_model(m: mujoco.MjModel) -> mujoco.MjModel:
    import copy
    return copy.deepcopy(m)


def _as_f64(p: PhysParams) -> PhysParams:
    return PhysParams(**{k: np.asarray(v, np.float64) for k, v in p.as_dict().items()})


def _get(d, f, i) -> float:
    return float(np.asarray(d[f]).reshape(-1)[i])


def _to_u(field: str, v: float) -> float:
    if field in POSITIVE:
        return float(np.log(v))
    if field in NONNEGATIVE:
        v = max(float(v), 1e-9)
        return float(v + np.log(-np.expm1(-v)))
    return float(v)


def _from_u(field: str, u: float) -> float:
    if field in POSITIVE:
        return float(np.exp(u))
    if field in NONNEGATIVE:
        return float(np.logaddexp(0.0, u))
    return float(u)


def _dvalue_du(field: str, u: float) -> float:
    if field in POSITIVE:
        return float(np.exp(u))
    if field in NONNEGATIVE:
        return float(1.0 / (1.0 + np.exp(-u)))
    return 1.0


# ---------------------------------------------------------------------------------- result
@dataclasses.dataclass(frozen=True)
class SysidResult:
    """What ``fit`` found. Values are physical (kg, N s/m, ...); ``*_u`` are unconstrained."""

    params: PhysParams
    """Full identified parameters (unfitted fields at their nominal values): pass to
    ``twinrl.envs.make(name, params=...)``."""
    latency: int
    """Identified action latency in control steps."""
    names: tuple[str, ...]
    """Fitted and known parameters, ``"field/element"``."""
    spec: tuple[tuple[str, int], ...]
    """``(PhysParams field, index)`` of each name."""
    initial: np.ndarray
    """Values the fit started from."""
    nominal: np.ndarray
    """Values of the simulator before the fit (the prior's centre for unidentifiable ones)."""
    values: np.ndarray
    """Identified values."""
    sd: np.ndarray
    """Posterior standard deviation (Laplace approximation, delta method to physical units)."""
    sd_u: np.ndarray
    """Posterior sd in unconstrained coordinates (about relative for log/softplus fields)."""
    identifiable: np.ndarray
    """Bool per parameter: the data pin it down (sd_u <= max_rel_sd, or held at its bound 0 with
    a finite one-sided sd); known ones are False."""
    status: tuple[str, ...]
    """Per parameter: ``identified``, ``known``, ``at bound 0 (sd one-sided)`` (value 0 up to
    softplus' floor; ``sd`` is how far above 0 the data still allow it), ``not identifiable
    (flat; left at nominal)``, ``not identifiable (no effect; at bound 0)`` or ``only in
    combination (flat direction k)``."""
    flat_directions: tuple[dict, ...]
    """Each flat eigen-direction of the Fisher information: its ``sd`` and ``loadings``."""
    loss: float
    """Mean robust loss per residual at the optimum (chosen latency)."""
    loss_by_latency: dict[int, float]
    loss_history: tuple[float, ...]
    """Mean loss per residual after each accepted iteration (all latencies, in order)."""
    history: tuple[dict, ...]
    """Per iteration: ``latency``, ``rollouts`` (cumulative), ``loss``, ``values``."""
    sim_rollouts: int
    """Window rollouts simulated in total (forward passes, gradient and Jacobian passes)."""
    n_windows: int
    residual_sd: np.ndarray
    """Sd of the residuals per observation dimension at the optimum (observation units)."""
    seconds: float
    config: SysidConfig
    theta_u: np.ndarray
    cov_u: np.ndarray
    """Posterior covariance in unconstrained coordinates (fitted parameters; known rows 0)."""
    cov_u_data: np.ndarray
    """Pseudo-inverse of the data's Fisher information (flat directions removed)."""
    bound_tests: dict[str, float] = dataclasses.field(default_factory=dict)
    """Each non-negative parameter tested at its bound 0: the (window-robust) likelihood ratio
    of holding it there; below ``config.bound_lr`` it was held (status ``at bound 0``)."""
    task: str | None = None
    """Registered task name of the env the fit ran on (None for an unregistered one)."""

    @property
    def system(self) -> System:
        """The identified twin: ``params`` and ``latency`` as a ``twinrl.envs.System``; pass to
        ``twinrl.envs.make(name, system=...)``."""
        return System(params=self.params, latency=self.latency, task=self.task)

    @property
    def table(self) -> list[dict[str, Any]]:
        """Rows: parameter, initial, identified, sd, identifiable, status."""
        return [dict(parameter=n, initial=float(i), identified=float(v), sd=float(s),
                     identifiable=bool(ok), status=st)
                for n, i, v, s, ok, st in zip(self.names, self.initial, self.values, self.sd,
                                              self.identifiable, self.status)]


def fit(env: Env, data, config: SysidConfig | None = None, rng: jax.Array | None = None,
        progress_fn: Callable[[int, dict], None] | None = None) -> SysidResult:
    """Identify ``PhysParams`` and the action latency of ``env``'s system from ``data``.

    Args:
      env: the simulated task (its ``params``, or the MJCF's, are the starting point).
      data: a ``twinrl.real.dataset.Dataset``, in-memory arrays (see ``windows_from_dataset``),
        ``Windows``, or a ``Problem`` already built on them.
      config: ``SysidConfig``.
      rng: unused by the deterministic LM fit (kept for the trainer signature; Adam is
        deterministic too).
      progress_fn: called ``progress_fn(iteration, metrics)`` after every iteration.
    """
    del rng
    config = config or SysidConfig()
    t_start = time.perf_counter()
    with jax.enable_x64(bool(config.float64)):
        prob = data if isinstance(data, Problem) else build_problem(env, data, config)
        c = prob.config
        hist, loss_hist, step = [], [], [0]

        def log(latency, theta, obj_mean):
            step[0] += 1
            rec = dict(latency=int(latency), rollouts=int(prob.rollouts), loss=float(obj_mean),
                       values=prob.values_of(theta))
            hist.append(rec)
            loss_hist.append(float(obj_mean))
            if progress_fn is not None:
                progress_fn(step[0], {k: v for k, v in rec.items() if k != "values"})

        fits = {}
        start = bool(c.estimate_start)
        q_rec, v_rec = prob.qpos0.copy(), prob.qvel0.copy()
        latencies = range(c.max_latency + 1) if c.latency is None else [int(c.latency)]
        for k in latencies:
            theta = prob.theta0.copy()
            if c.optimizer in ("adam", "adam+lm"):
                theta = _adam(prob, theta, k, lambda th, v: log(k, th, v))
            prob.qpos0, prob.qvel0 = q_rec, v_rec
            if c.optimizer in ("lm", "adam+lm"):
                theta = _lm(prob, theta, k, prob.free, lambda th, v: log(k, th, v), start)
            r = prob.residuals(theta, k)
            fits[k] = (prob.data_loss(r) / r.size, theta, prob.qpos0, prob.qvel0)
        latency = min(fits, key=lambda k: fits[k][0])
        theta = fits[latency][1]
        prob.qpos0, prob.qvel0 = fits[latency][2], fits[latency][3]

        # Identifiability and uncertainty at the optimum; non-negative parameters the data allow
        # at 0 are held there, single-parameter flat directions are put back to nominal and the
        # rest refitted.
        free = prob.free.copy()
        info = _laplace(prob, theta, latency, free, start)
        bound: list[int] = []
        tests: dict = {}
        if c.bound_lr > 0:
            theta, free, bound, info, tests = _bound_tests(prob, theta, latency, free, start, info,
                                                    lambda th, v: log(latency, th, v))
        single = sorted({max(d["loadings"], key=lambda j: abs(d["loadings"][j]))
                         for d in info["flat"] if d["sd"] > c.flat_sd
                         and max(x * x for x in d["loadings"].values()) > 0.5})
        if single:
            free_after = free.copy()
            for j in single:
                free_after[j] = False
                theta[j] = _to_u(prob.spec[j][0], max(prob.nominal[j], 1e-9))
            if free_after.any():
                theta = _lm(prob, theta, latency, free_after, lambda th, v: log(latency, th, v),
                            start)
            info = _laplace(prob, theta, latency, free_after, start, extra_flat=info["flat"],
                            reset=single, bound=bound)
        r = prob.residuals(theta, latency)
        loss = prob.data_loss(r) / r.size
        fits[latency] = (loss,) + fits[latency][1:]

        values = prob.values_of(theta)
        sd_u = info["sd_u"]
        sd = np.array([abs(_dvalue_du(f, t)) * s for (f, _), t, s in zip(prob.spec, theta, sd_u)])
        status, ident = [], []
        combo_of = {j: k for k, d in enumerate(info["flat"]) for j in d["loadings"]
                    if j not in info["reset"] and d["loadings"][j] ** 2 > 0.05}
        for j, n in enumerate(prob.names):
            if not prob.free[j]:
                status.append("known")
            elif j in info["reset"]:
                status.append("not identifiable (flat; left at nominal)")
            elif j in bound:
                status.append("at bound 0 (sd one-sided)" if math.isfinite(sd[j]) else
                              "not identifiable (no effect; at bound 0)")
            elif sd_u[j] > c.max_rel_sd:
                status.append(f"only in combination (flat direction {combo_of[j]})" if j in combo_of
                              else "not identifiable (sd above threshold)")
            else:
                status.append("identified")
            ident.append(status[-1] == "identified" or status[-1].startswith("at bound"))
        flat = tuple(dict(sd=d["sd"], loadings={prob.names[j]: float(l) for j, l in
                                                 d["loadings"].items()}) for d in info["flat"])
        resid_sd = np.sqrt(np.mean(r.reshape(-1, r.shape[-1]) ** 2, axis=0)) * prob.scale
        return SysidResult(
            params=prob.params_of(theta), latency=int(latency), names=prob.names,
            spec=tuple(prob.spec),
            initial=prob.initial.copy(), nominal=prob.nominal.copy(), values=values, sd=sd,
            sd_u=sd_u, identifiable=np.array(ident), status=tuple(status), flat_directions=flat,
            loss=float(loss), loss_by_latency={k: float(v[0]) for k, v in fits.items()},
            loss_history=tuple(loss_hist), history=tuple(hist), sim_rollouts=int(prob.rollouts),
            n_windows=prob.n_windows, residual_sd=resid_sd, seconds=time.perf_counter() - t_start,
            config=c, theta_u=np.asarray(theta), cov_u=info["cov"], cov_u_data=info["cov_data"],
            bound_tests=tests, task=_task_name(env))


def _task_name(env) -> str | None:
    name = getattr(env, "name", None)
    return name if name in TASKS else None


# ---------------------------------------------------------------------------------- optimisers
def _objective(prob: Problem, r: np.ndarray, theta, kappa: float) -> float:
    return prob.data_loss(r) + kappa * prob.prior(theta)


def _normal_terms(r, J, Jx, w, fi):
    """Blocks of the weighted normal equations, per window for the start states."""
    n = r.shape[0]
    rv, Jt = r.reshape(n, -1), J.reshape(n, -1, J.shape[-1])[..., fi]
    wv = w.reshape(n, -1)
    Htt = np.einsum("nmp,nm,nmq->pq", Jt, wv, Jt)
    gt = np.einsum("nmp,nm->p", Jt, wv * rv)
    if Jx is None:
        return Htt, gt, None, None, None, np.einsum("nmp,nm->np", Jt, wv * rv)
    Jxx = Jx.reshape(n, -1, Jx.shape[-1])
    Htx = np.einsum("nmp,nm,nmk->npk", Jt, wv, Jxx)
    Hxx = np.einsum("nmk,nm,nml->nkl", Jxx, wv, Jxx)
    gx = np.einsum("nmk,nm->nk", Jxx, wv * rv)
    return Htt, gt, Htx, Hxx, gx, np.einsum("nmp,nm->np", Jt, wv * rv)


def _lm(prob: Problem, theta, latency: int, free: np.ndarray, log, start: bool) -> np.ndarray:
    """Levenberg-Marquardt with IRLS weights for the robust loss and the Gaussian prior; with
    ``start``, every window's start state is estimated too (eliminated per window by the Schur
    complement, as in bundle adjustment), and ``prob.qpos0/qvel0`` are updated."""
    c = prob.config
    theta = np.array(theta, np.float64)
    q, v = prob.qpos0.copy(), prob.qvel0.copy()
    nq = prob.sim.nq

    def jac():
        prob.qpos0, prob.qvel0 = q, v
        return prob.jacobian(theta, latency, start=True) if start else (
            *prob.jacobian(theta, latency), None)

    r, J, Jx = jac()
    lam = c.lm_damping
    fi = np.flatnonzero(free)
    for _ in range(c.lm_steps):
        # The prior is worth one residual's mean loss per parameter at the current fit (about one
        # unit of -2 log-likelihood per prior sd^2): negligible against thousands of residuals,
        # decisive only along flat directions. Weighed at the starting loss instead, it kept that
        # weight while the loss fell 100-fold and held a zero friction loss at a positive value.
        kappa = 2.0 * prob.data_loss(r) / r.size + 1e-12
        obj = _objective(prob, r, theta, kappa)
        prior_prec = kappa / c.prior_sd ** 2
        _, w = _rho(r, c.loss, c.loss_scale)
        Htt, gt, Htx, Hxx, gx, _ = _normal_terms(r, J, Jx, w, fi)
        Htt = Htt + prior_prec * np.eye(len(fi))
        gt = gt + prior_prec * (theta[fi] - prob.theta0[fi])
        improved, rc, rel = False, r, 0.0
        for _ in range(12):
            A = Htt + lam * np.diag(np.maximum(np.diag(Htt), 1e-12))
            try:
                if Jx is None:
                    dt, dx = -np.linalg.solve(A, gt), None
                else:
                    Ax = Hxx + lam * np.einsum("nk,kl->nkl", np.maximum(
                        np.einsum("nkk->nk", Hxx), 1e-12), np.eye(Hxx.shape[-1]))
                    Ai = np.linalg.inv(Ax)
                    S = A - np.einsum("npk,nkl,nql->pq", Htx, Ai, Htx)
                    rhs = gt - np.einsum("npk,nkl,nl->p", Htx, Ai, gx)
                    dt = -np.linalg.solve(S, rhs)
                    dx = -np.einsum("nkl,nl->nk", Ai, gx + np.einsum("npl,p->nl", Htx, dt))
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            cand = theta.copy()
            cand[fi] += dt
            qc, vc = (q, v) if dx is None else (q + dx[:, :nq], v + dx[:, nq:])
            rc = prob.residuals(cand, latency, qc, vc)
            oc = _objective(prob, rc, cand, kappa) if np.all(np.isfinite(rc)) else np.inf
            if oc < obj:
                improved = True
                rel = (obj - oc) / max(abs(obj), 1e-300)
                theta, obj, q, v = cand, oc, qc, vc
                lam = max(lam / 3.0, 1e-9)
                break
            lam *= 4.0
        log(theta, prob.data_loss(rc) / rc.size)
        if not improved or rel < c.tol or np.max(np.abs(dt)) < c.step_tol:
            break
        r, J, Jx = jac()
    prob.qpos0, prob.qvel0 = q, v
    return theta


def _adam(prob: Problem, theta, latency: int, log) -> np.ndarray:
    c = prob.config
    theta = jnp.asarray(theta)
    opt = optax.adam(c.adam_lr)
    state = opt.init(theta)
    mask = jnp.asarray(prob.free, theta.dtype)
    n_res = prob.n_windows * (c.window + 1) * prob.windows.targets.shape[-1]
    best = (np.inf, theta)
    for _ in range(c.adam_steps):
        v, g = prob.loss_and_grad(theta, latency)
        mean = v / n_res
        if np.isfinite(mean) and mean < best[0]:
            best = (mean, theta)
        g = jnp.where(jnp.isfinite(jnp.asarray(g)), jnp.asarray(g), 0.0) / n_res * mask
        upd, state = opt.update(g, state)
        theta = optax.apply_updates(theta, upd)
        log(np.asarray(theta), mean)
    return np.asarray(best[1])


def _bound_tests(prob: Problem, theta, latency: int, free: np.ndarray, start: bool, info: dict,
                 log) -> tuple[np.ndarray, np.ndarray, list[int], dict, dict]:
    """Hold each fitted non-negative parameter at its bound 0 where the data allow it.

    Softplus coordinates cannot reach 0: the value's slope vanishes there, and the prior (centred
    on ``nonneg_init``) pulls back, so a damping or friction loss whose truth is 0 stalls at a
    small positive value and other parameters make up for it (a hinge friction loss of 0.0036
    taking 14 % off the hinge damping). Each candidate, most compatible with 0 first, is refitted
    held at 0; the bound is kept when the data's deviance (2 sum rho / sigma_d^2) rises by less
    than ``bound_lr`` after scaling by the Gauss-Newton / sandwich variance ratio (the naive
    likelihood ratio overstates the evidence of residuals correlated inside a window) -- a
    likelihood-ratio test against the boundary null 0.5 chi2_0 + 0.5 chi2_1.
    Returns the new ``theta``, ``free``, the bound indices, their ``_laplace`` info and the
    scaled likelihood ratio of each tested parameter (by name)."""
    c = prob.config
    cand = [int(j) for j in np.flatnonzero(free) if prob.spec[j][0] in NONNEGATIVE]
    if not cand:
        return theta, free, [], info, {}
    var = info["var"]

    def deviance(r):
        return 2.0 * float(np.sum(_rho(r, c.loss, c.loss_scale)[0].sum(axis=(0, 1)) / var))

    def z(j):
        f = prob.spec[j][0]
        return _from_u(f, theta[j]) / max(_dvalue_du(f, theta[j]) * info["sd_u"][j], 1e-300)

    d_cur = deviance(prob.residuals(theta, latency))
    bound: list[int] = []
    tests = {}
    for j in sorted(cand, key=z):
        q, v = prob.qpos0.copy(), prob.qvel0.copy()
        trial_free = free.copy()
        trial_free[j] = False
        th = theta.copy()
        th[j] = _to_u(prob.spec[j][0], 0.0)
        if trial_free.any():
            th = _lm(prob, th, latency, trial_free, lambda *_: None, start)
        r = prob.residuals(th, latency)
        d = deviance(r)
        trial = _laplace(prob, th, latency, trial_free, start, bound=bound + [j])
        tests[prob.names[j]] = lr = (d - d_cur) * float(trial["gn_ratio"][j])
        if lr < c.bound_lr:
            theta, free, d_cur, info = th, trial_free, d, trial
            bound.append(j)
            log(theta, prob.data_loss(r) / r.size)
        else:
            prob.qpos0, prob.qvel0 = q, v
    return theta, free, bound, info, tests


# ---------------------------------------------------------------------------------- Laplace
def _laplace(prob: Problem, theta, latency: int, free: np.ndarray, start: bool, extra_flat=(),
             reset=(), bound=()) -> dict:
    """Fisher information (start states marginalised), flat directions, posterior covariance.

    ``bound``: parameters held at their bound 0 (not in ``free``). Softplus coordinates carry no
    information there, so their columns are taken in physical units: they join the covariance
    (one-sided sd, and the others' sd marginal over them: the truth may lie anywhere in
    [0, a few sd]) without a prior, and stay out of the flat-direction analysis."""
    c = prob.config
    if start:
        r, J, Jx = prob.jacobian(theta, latency, start=True)
    else:
        (r, J), Jx = prob.jacobian(theta, latency), None
    n, _, o, P = J.shape
    fi = np.flatnonzero(free)
    bound = [int(j) for j in bound]
    idx = np.concatenate([fi, np.asarray(bound, int)])
    nf = len(fi)
    # d(value)/du of each column: 1 for free ones (kept in u), softplus' slope at the bound ones.
    dv = np.ones(len(idx))
    dv[nf:] = [_dvalue_du(prob.spec[j][0], theta[j]) for j in bound]
    J = J[..., idx] / dv
    cols = np.arange(len(idx))
    _, w = _rho(r, c.loss, c.loss_scale)
    # Residual variance per observation dimension (robust: the IRLS-weighted mean square).
    n_x = 0 if Jx is None else n * Jx.shape[-1]
    dof = max(r.size - len(idx) - n_x, 1)
    var = np.maximum(np.sum(w * r * r, axis=(0, 1)) / (dof / o), 1e-300)
    wt = w / var
    F, _, Htx, Hxx, _, g = _normal_terms(r, J, Jx, wt, cols)
    if Jx is not None:
        Hxx_i = np.linalg.pinv(Hxx)
        F = F - np.einsum("npk,nkl,nql->pq", Htx, Hxx_i, Htx)
        gx = np.einsum("nmk,nm->nk", Jx.reshape(n, -1, Jx.shape[-1]), (wt * r).reshape(n, -1))
        g = g - np.einsum("npk,nkl,nl->np", Htx, Hxx_i, gx)
    F = 0.5 * (F + F.T)
    eig, V = np.linalg.eigh(F[:nf, :nf])
    flat = []
    for lam, vec in zip(eig, V.T):
        sd = 1.0 / math.sqrt(lam) if lam > 0 else math.inf
        if sd > c.max_rel_sd:
            flat.append(dict(sd=float(sd), loadings={int(fi[k]): float(x) for k, x in
                                                     enumerate(vec) if abs(x) > 1e-3}))
    keep = eig * c.max_rel_sd ** 2 > 1.0
    cov_data_f = (V[:, keep] / eig[keep]) @ V[:, keep].T
    # A bound parameter the data do not see at all has no (one-sided) sd: it is left out of the
    # joint inversion and reported with an infinite one.
    blind = np.zeros(len(idx), bool)
    blind[nf:] = np.diag(F)[nf:] <= 1e-12 * max(float(np.max(np.diag(F))), 1e-300)
    use = ~blind
    prior = np.where(np.arange(len(idx)) < nf, 1.0 / c.prior_sd ** 2, 0.0)[use]
    Fu, gu = F[np.ix_(use, use)], g[:, use]
    Hinv = np.linalg.inv(Fu + np.diag(prior))
    if c.uncertainty == "sandwich":
        # Scores clustered by window (residuals of one window share its start-state error), with
        # the small-sample factor n / (n - p); the prior keeps its own variance in flat directions.
        S = gu.T @ gu * (n / max(n - len(idx), 1))
        cov_f = Hinv @ (S + np.diag(prior)) @ Hinv
        Sf = g[:, :nf].T @ g[:, :nf] * (n / max(n - len(idx), 1))
        cov_data_f = cov_data_f @ Sf @ cov_data_f
    else:
        cov_f = Hinv
    # Gauss-Newton over sandwich variance of each parameter: how much the naive likelihood
    # overstates the evidence (correlated residuals inside a window); scales likelihood ratios.
    sel = idx[use]
    gn_ratio = np.ones(P)
    gn_ratio[sel] = np.diag(Hinv) / np.maximum(np.diag(cov_f), 1e-300)
    # Back to unconstrained coordinates (bound rows: physical / slope, huge but consistent).
    cov_f = cov_f / np.outer(dv[use], dv[use])
    cov = np.zeros((P, P))
    cov[np.ix_(sel, sel)] = cov_f
    cov_data = np.zeros((P, P))
    cov_data[np.ix_(fi, fi)] = cov_data_f
    sd_u = np.sqrt(np.maximum(np.diag(cov), 0.0))
    for j in idx[blind]:
        sd_u[j] = math.inf
    for j in reset:
        sd_u[j] = c.prior_sd
    return dict(sd_u=sd_u, cov=cov, cov_data=cov_data, flat=list(extra_flat) or flat,
                reset=tuple(reset), var=var, gn_ratio=gn_ratio)


# ---------------------------------------------------------------------------------- evaluation
def compare_to_truth(result: SysidResult, truth: PhysParams,
                     true_latency: int | None = None) -> list[dict[str, Any]]:
    """Evaluation only: each fitted parameter against its true value.

    ``truth`` is the real twin's true ``PhysParams`` (its oracle's ``params``), which learning
    code never sees. Rows: parameter, truth, identified, sd, rel_err (|identified - truth| /
    |truth|; absolute error where the truth is 0), covered (|error| <= 3 sd), identifiable, and
    -- where the parameter is only identifiable in combination (overall scale) -- ``aligned``:
    the identified value after the one common scale factor that best matches the truth, with its
    ``aligned_rel_err`` and ``aligned_covered`` (against the sd along the identifiable
    directions). A ``latency`` row is added when ``true_latency`` is given.
    """
    t = _as_f64(truth).as_dict()
    rows = []
    combo = [j for j, s in enumerate(result.status) if s.startswith("only in combination")]
    aligned = result.values.copy()
    if combo:
        true_v = np.array([_get(t, *_split(n, result)) for n in np.array(result.names)[combo]])
        ok = (true_v > 0) & (result.values[combo] > 0)
        logc = float(np.mean(np.log(true_v[ok] / result.values[combo][ok]))) if ok.any() else 0.0
        aligned[combo] = result.values[combo] * math.exp(logc)
    sd_data = np.sqrt(np.maximum(np.diag(result.cov_u_data), 0.0))
    for j, name in enumerate(result.names):
        tv = _get(t, *_split(name, result))
        v, s = float(result.values[j]), float(result.sd[j])
        err = abs(v - tv)
        row = dict(parameter=name, truth=tv, identified=v, sd=s,
                   rel_err=err / abs(tv) if tv != 0 else err, covered=bool(err <= 3 * s + 1e-12),
                   identifiable=bool(result.identifiable[j]), status=result.status[j])
        if j in combo:
            f = _split(name, result)[0]
            s_al = abs(_dvalue_du(f, result.theta_u[j])) * sd_data[j] * aligned[j] / max(v, 1e-300)
            e_al = abs(aligned[j] - tv)
            row.update(aligned=float(aligned[j]), aligned_sd=float(s_al),
                       aligned_rel_err=e_al / abs(tv) if tv != 0 else e_al,
                       aligned_covered=bool(e_al <= 3 * s_al + 1e-12))
        rows.append(row)
    if true_latency is not None:
        rows.append(dict(parameter="latency", truth=int(true_latency), identified=result.latency,
                         sd=0.0, rel_err=float(result.latency != true_latency),
                         covered=result.latency == true_latency, identifiable=True,
                         status="identified"))
    return rows


def _split(name: str, result: SysidResult) -> tuple[str, int]:
    return result.spec[result.names.index(name)]


def print_result(result: SysidResult, truth_rows: list[dict] | None = None,
                 title: str = "sysid") -> None:
    """Print the report table (with truth columns when ``compare_to_truth`` rows are given)."""
    from twinrl import report
    if truth_rows is None:
        cols = ["parameter", "initial", "identified", "sd", "identifiable"]
        rows = [[r["parameter"], r["initial"], r["identified"], r["sd"], r["status"]]
                for r in result.table]
    else:
        cols = ["parameter", "initial", "identified", "sd", "identifiable", "truth", "rel err",
                "|err|<=3sd"]
        init = {r["parameter"]: r["initial"] for r in result.table}
        rows = [[r["parameter"], init.get(r["parameter"], "-"), r["identified"], r["sd"],
                 r["status"], r["truth"], r["rel_err"], "yes" if r["covered"] else "NO"]
                for r in truth_rows]
    rows.append(["latency", "-", result.latency, "-", "chosen by loss", "", "", ""][:len(cols)])
    report.print_table(f"{title}: loss {result.loss:.3g}, {result.n_windows} windows, "
                       f"{result.sim_rollouts} window rollouts, {result.seconds:.1f} s",
                       cols, rows)
