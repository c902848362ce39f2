"""Gradient-free baselines for Real2Sim: CMA-ES on the sysid objective.

CMA-ES (Hansen & Ostermeier 2001; the ``cma`` package, pinned 4.5.0) is the usual black-box
answer to system identification (SAM-RL compares against it). It minimises *the same function*
as ``twinrl.real2sim.sysid.fit``: the mean robust loss of the multiple-shooting residuals of a
``sysid.Problem``, over the same unconstrained coordinates (``PhysParams.unconstrain``), from the
same start, with window start states taken from the recorded observations. The one thing it does
without is the gradient, so ``CmaesResult.sim_rollouts`` (windows simulated, counted by the
``Problem`` exactly as for the gradient fit) is the price of that; ``bench/sysid.py`` compares the
two.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable

import jax
import numpy as np

from twinrl.envs.base import Env
from twinrl.physics import PhysParams
from twinrl.real2sim.sysid import Problem, SysidConfig, build_problem

__all__ = ["CmaesConfig", "CmaesResult", "cmaes_fit"]


@dataclasses.dataclass(frozen=True)
class CmaesConfig:
    """CMA-ES settings (the objective's settings come from a ``SysidConfig``)."""

    sigma0: float = 0.3
    """Initial step size in unconstrained coordinates (about a 30 % relative change)."""
    popsize: int | None = None
    """Candidates per generation (default: CMA-ES's 4 + 3 ln(n))."""
    max_evals: int = 3000
    """Budget of objective evaluations (each simulates every window once)."""
    tolfun: float = 1e-12
    """Stop when the best losses of recent generations differ by less than this."""


@dataclasses.dataclass(frozen=True)
class CmaesResult:
    params: PhysParams
    latency: int
    names: tuple[str, ...]
    values: np.ndarray
    """Best values found (physical units)."""
    loss: float
    """Mean robust loss per residual at the best candidate."""
    loss_by_latency: dict[int, float]
    history: tuple[dict, ...]
    """Per generation: ``latency``, ``rollouts`` (cumulative), ``loss`` (best so far), ``values``."""
    sim_rollouts: int
    evaluations: int
    seconds: float


def cmaes_fit(env: Env, data, config: SysidConfig | None = None,
              cmaes: CmaesConfig | None = None, seed: int = 0,
              progress_fn: Callable[[int, dict], None] | None = None) -> CmaesResult:
    """Minimise the sysid objective of ``config`` on ``data`` with CMA-ES, for each latency.

    ``data`` as for ``sysid.fit`` (a Dataset, arrays, ``Windows`` or a ``Problem``). Start
    states are the recorded ones (CMA-ES cannot carry a start state per window as free
    variables); compare with ``sysid.fit`` under ``SysidConfig(estimate_start=False)``.
    """
    import cma

    config = config or SysidConfig(estimate_start=False)
    cmaes = cmaes or CmaesConfig()
    t0 = time.perf_counter()
    with jax.enable_x64(bool(config.float64)):
        prob = data if isinstance(data, Problem) else build_problem(env, data, config)
        c = prob.config
        free = prob.free
        q_rec, v_rec = prob.qpos0.copy(), prob.qvel0.copy()
        hist, fits, gen = [], {}, 0
        latencies = range(c.max_latency + 1) if c.latency is None else [int(c.latency)]
        for k in latencies:
            prob.qpos0, prob.qvel0 = q_rec, v_rec
            theta = prob.theta0.copy()
            opts = {"seed": int(seed) + 1, "maxfevals": int(cmaes.max_evals), "verbose": -9,
                    "tolfun": cmaes.tolfun, "tolx": 1e-10}
            if cmaes.popsize:
                opts["popsize"] = int(cmaes.popsize)
            es = cma.CMAEvolutionStrategy(theta[free], cmaes.sigma0, opts)
            best = (np.inf, theta)
            while not es.stop():
                xs = es.ask()
                losses = []
                for x in xs:
                    th = theta.copy()
                    th[free] = x
                    v = prob.loss(th, k)
                    losses.append(v if np.isfinite(v) else 1e30)
                    if v < best[0]:
                        best = (float(v), th)
                es.tell(xs, losses)
                gen += 1
                rec = dict(latency=k, rollouts=int(prob.rollouts), loss=best[0],
                           values=prob.values_of(best[1]))
                hist.append(rec)
                if progress_fn is not None:
                    progress_fn(gen, {kk: vv for kk, vv in rec.items() if kk != "values"})
            fits[k] = best
        latency = min(fits, key=lambda kk: fits[kk][0])
        loss, theta = fits[latency]
        params = prob.params_of(theta)
        return CmaesResult(params=params, latency=int(latency), names=prob.names,
                           values=prob.values_of(theta), loss=float(loss),
                           loss_by_latency={kk: float(v[0]) for kk, v in fits.items()},
                           history=tuple(hist), sim_rollouts=int(prob.rollouts),
                           evaluations=int(prob.rollouts // max(prob.n_windows, 1)),
                           seconds=time.perf_counter() - t0)
