"""``fit``: identify ``PhysParams`` and the action latency of a task from its real transitions
(the method is ``twinrl.real2sim.sysid``'s docstring), returning a ``SysidResult`` whose
``system`` is the identified ``twinrl.envs.System``.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable

import jax
import numpy as np

from twinrl.envs.base import Env
from twinrl.envs.registry import TASKS
from twinrl.envs.system import System
from twinrl.physics import PhysParams
from twinrl.real2sim.sysid.config import SysidConfig
from twinrl.real2sim.sysid.optimise import adam_fit, levenberg_marquardt
from twinrl.real2sim.sysid.problem import Problem, build_problem, dvalue_du, to_unconstrained
from twinrl.real2sim.sysid.uncertainty import bound_tests, laplace

__all__ = ["SysidResult", "fit"]


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

    def summary(self) -> dict[str, Any]:
        """What ``twinrl sysid`` records of the fit in ``summary.json``: ``latency``, ``loss``,
        ``sim_rollouts``, ``seconds``, ``table`` and every ``params`` field as lists."""
        return {"latency": self.latency, "loss": self.loss, "sim_rollouts": self.sim_rollouts,
                "seconds": self.seconds, "table": self.table,
                "params": {k: v.tolist() for k, v in self.params.as_dict().items()}}


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
                theta = adam_fit(prob, theta, k, lambda th, v: log(k, th, v))
            prob.qpos0, prob.qvel0 = q_rec, v_rec
            if c.optimizer in ("lm", "adam+lm"):
                theta = levenberg_marquardt(prob, theta, k, prob.free,
                                            lambda th, v: log(k, th, v), start)
            r = prob.residuals(theta, k)
            fits[k] = (prob.data_loss(r) / r.size, theta, prob.qpos0, prob.qvel0)
        latency = min(fits, key=lambda k: fits[k][0])
        theta = fits[latency][1]
        prob.qpos0, prob.qvel0 = fits[latency][2], fits[latency][3]

        # Identifiability and uncertainty at the optimum; non-negative parameters the data allow
        # at 0 are held there, single-parameter flat directions are put back to nominal and the
        # rest refitted.
        free = prob.free.copy()
        info = laplace(prob, theta, latency, free, start)
        bound: list[int] = []
        tests: dict = {}
        if c.bound_lr > 0:
            theta, free, bound, info, tests = bound_tests(prob, theta, latency, free, start, info,
                                                    lambda th, v: log(latency, th, v))
        single = sorted({max(d["loadings"], key=lambda j: abs(d["loadings"][j]))
                         for d in info["flat"] if d["sd"] > c.flat_sd
                         and max(x * x for x in d["loadings"].values()) > 0.5})
        if single:
            free_after = free.copy()
            for j in single:
                free_after[j] = False
                theta[j] = to_unconstrained(prob.spec[j][0], max(prob.nominal[j], 1e-9))
            if free_after.any():
                theta = levenberg_marquardt(prob, theta, latency, free_after,
                                            lambda th, v: log(latency, th, v), start)
            info = laplace(prob, theta, latency, free_after, start, extra_flat=info["flat"],
                            reset=single, bound=bound)
        r = prob.residuals(theta, latency)
        loss = prob.data_loss(r) / r.size
        fits[latency] = (loss,) + fits[latency][1:]

        values = prob.values_of(theta)
        sd_u = info["sd_u"]
        sd = np.array([abs(dvalue_du(f, t)) * s for (f, _), t, s in zip(prob.spec, theta, sd_u)])
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
