"""``SysidConfig`` (how ``fit`` identifies parameters) and the names of fittable parameters.

A parameter is named ``"field/element"`` (``"mass/cart"``, ``"damping/slider"``): a ``PhysParams``
field (``FITTABLE``) and a body, dof, actuator or geom of the MJCF; ``param_names`` lists them for
a task, ``parse_param`` turns one into its ``(field, index)`` (part of ``twinrl.real2sim.sysid``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

import mujoco

from twinrl.envs.base import Env

__all__ = ["FITTABLE", "DEFAULT_FIELDS", "LOSSES", "OPTIMIZERS", "UNCERTAINTIES", "SysidConfig",
           "param_names", "default_param_names", "parse_param"]


FITTABLE = ("mass", "damping", "armature", "frictionloss", "friction", "gain", "gravity")
"""``PhysParams`` fields sysid can fit, by element name ``"field/element"``."""


DEFAULT_FIELDS = ("mass", "damping", "frictionloss", "gain")


LOSSES = ("huber", "cauchy", "l2")


OPTIMIZERS = ("lm", "adam", "adam+lm")


UNCERTAINTIES = ("sandwich", "gauss_newton")


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
    start_prior_sd: float = 1.0
    """With ``estimate_start``: sd of the Gaussian prior of each estimated start state around
    the recorded one, per tangent coordinate in SI units (m, rad, m/s, rad/s), weighed like the
    parameters' prior. Negligible where the data pin the state (a recorded joint: to the mm);
    it holds what no residual sees (a flat disc's spin about its axis) where it was recorded."""
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
    observation_weights: tuple[float, ...] | None = None
    """Weight of each observation dimension's residual (after normalising by its spread); 0
    leaves a dimension out. E.g. push identified from full states (``observation="state"``) on
    its planar motion only: the box's tilt and rocking in its soft floor contacts differ between
    engines (MuJoCo C's and MJX's contact solutions), which no parameter explains. Default: all 1."""
    batch_windows: int = 64
    """Windows per vmapped batch (fixed, so one compile serves every dataset size)."""
    max_windows: int | None = None
    """Use at most this many windows (evenly spread); default all."""

    def __post_init__(self):
        def need(ok, what):
            if not ok:
                raise ValueError(f"SysidConfig: {what}")
        need(int(self.window) >= 1, f"window must be >= 1, got {self.window}")
        need(self.stride is None or int(self.stride) >= 1,
             f"stride must be >= 1, got {self.stride}")
        need(int(self.max_latency) >= 0, f"max_latency must be >= 0, got {self.max_latency}")
        need(self.latency is None or 0 <= int(self.latency) <= int(self.max_latency),
             f"latency must be in 0..max_latency={self.max_latency}, got {self.latency}")
        need(self.loss in LOSSES, f"loss must be one of {LOSSES}, got {self.loss!r}")
        need(self.optimizer in OPTIMIZERS,
             f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        need(self.uncertainty in UNCERTAINTIES,
             f"uncertainty must be one of {UNCERTAINTIES}, got {self.uncertainty!r}")
        for name in ("loss_scale", "prior_sd", "start_prior_sd", "flat_sd", "nonneg_init",
                     "frictionloss_floor", "max_rel_sd", "adam_lr", "lm_damping"):
            v = getattr(self, name)
            need(math.isfinite(v) and v > 0, f"{name} must be finite and > 0, got {v}")
        need(math.isfinite(self.bound_lr) and self.bound_lr >= 0,
             f"bound_lr must be finite and >= 0, got {self.bound_lr}")
        need(int(self.batch_windows) >= 1, f"batch_windows must be >= 1, got {self.batch_windows}")
        need(self.max_windows is None or int(self.max_windows) >= 1,
             f"max_windows must be >= 1, got {self.max_windows}")
        if self.observation_weights is not None:
            w = tuple(float(x) for x in self.observation_weights)
            need(all(math.isfinite(x) and x >= 0 for x in w) and any(w),
                 f"observation_weights must be finite, >= 0 and not all 0, got {w}")
            object.__setattr__(self, "observation_weights", w)
        for item in self.known:
            need(len(item) == 2 and math.isfinite(float(item[1])),
                 f"known entries are (name, finite value) pairs, got {item!r}")


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


def default_param_names(env: Env) -> tuple[str, ...]:
    m = env.sim.mj_model
    names = [f"mass/{e}" for e, w in zip(_element_names(m, "mass"), m.body_mass[1:]) if w > 0]
    return tuple(names) + param_names(env, ("damping", "frictionloss", "gain"))


def parse_param(env: Env, name: str) -> tuple[str, int]:
    field, _, element = str(name).partition("/")
    if field not in FITTABLE:
        raise ValueError(f"parameter {name!r}: field {field!r} cannot be fitted; fittable "
                         f"fields: {', '.join(FITTABLE)}")
    elements = _element_names(env.sim.mj_model, field)
    if element not in elements:
        raise ValueError(f"parameter {name!r}: {env.sim.name} has no {field} element "
                         f"{element!r}; allowed: {', '.join(f'{field}/{e}' for e in elements)}")
    return field, elements.index(element)
