"""Levenberg-Marquardt, the loop both Real2Sim fits share: system identification
(``twinrl.real2sim.sysid``: IRLS weights of a robust loss, a Gaussian prior, per-window start
states eliminated by the Schur complement) and visual Real2Sim (``twinrl.real2sim.visual``: a plain
dense solve on a rendered residual).

What is shared is the damping schedule and its bookkeeping (Marquardt 1963; Nocedal & Wright,
Sec. 10.3): at each iteration the caller *linearises* the problem at the current point (builds its
damped normal equations however it likes) and the loop

1. solves them with the current damping ``lam`` (a singular system, ``np.linalg.LinAlgError``,
   multiplies ``lam`` by ``singular_increase`` and tries again),
2. evaluates the candidate's *actual* cost, and accepts it only if that cost is finite and lower
   than the current one; a rejected step multiplies ``lam`` by ``increase`` (towards a short
   gradient step) and tries again, at most ``tries`` times,
3. after an accepted step divides ``lam`` by ``decrease`` (towards Gauss-Newton, floored at
   ``min_damping``).

It stops when no step of an iteration lowers the cost, when an accepted step lowers it by at most
``rtol`` times the cost before it or ``rtol_initial`` times the first cost, when the step is
smaller than ``step_tol`` (by the caller's ``step_size``), or after ``iterations``. Every iteration
is logged (cost, damping, accepted, tries) and reported to ``callback``.

What a fit supplies, ``linearise(x) -> Linearisation(cost, solve, evaluate)``, keeps its own
structure: the point ``x`` is whatever the fit carries (sysid: parameters and start states; visual:
the flat parameters and their residuals), and ``cost``/``evaluate`` may re-weight the problem at
every linearisation (sysid's IRLS weights and prior scale), since a candidate is only ever compared
with the cost of the same linearisation.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numpy as np

__all__ = ["Linearisation", "Result", "minimise"]


class Linearisation(NamedTuple):
    """The problem linearised at the current point ``x`` by the caller."""

    cost: float
    """The cost at ``x`` (under this linearisation's weights)."""
    solve: Callable[[float], Any]
    """``lam -> step``: the damped normal equations solved (may raise ``np.linalg.LinAlgError``)."""
    evaluate: Callable[[Any], tuple[Any, float]]
    """``step -> (candidate point, its cost)`` under the same weights as ``cost`` (a non-finite
    cost is a rejected step)."""


class Result(NamedTuple):
    """What ``minimise`` found."""

    x: Any
    """The last accepted point (``x0`` if no step was accepted)."""
    cost0: float
    """The cost at ``x0`` (first linearisation)."""
    cost: float
    """The cost at ``x`` (under the weights of the linearisation that accepted it)."""
    iterations: int
    """Linearisations made (the last one may have found no step)."""
    stop: str
    """Why it stopped: ``"no decrease"``, ``"small decrease"``, ``"small step"`` or
    ``"iterations"``."""
    log: tuple[dict, ...]
    """Per iteration: ``iteration``, ``cost`` (at the point kept), ``damping`` (after the
    update), ``accepted``, ``tries`` (solves attempted)."""


def minimise(linearise: Callable[[Any], Linearisation], x0: Any, *, damping: float,
             iterations: int, tries: int = 10, increase: float = 4.0, decrease: float = 3.0,
             min_damping: float = 1e-9, singular_increase: float = 10.0, rtol: float = 0.0,
             rtol_initial: float = 0.0, step_tol: float = 0.0,
             step_size: Callable[[Any], float] | None = None,
             callback: Callable[[Any, dict], None] | None = None) -> Result:
    """Levenberg-Marquardt from ``x0`` with the damping schedule of the module docstring."""
    if not (damping > 0 and iterations >= 1 and tries >= 1 and increase > 1 and decrease > 1):
        raise ValueError(f"minimise: needs damping > 0, iterations >= 1, tries >= 1, "
                         f"increase > 1, decrease > 1; got {damping}, {iterations}, {tries}, "
                         f"{increase}, {decrease}")
    x, lam, log = x0, float(damping), []
    cost0 = cost = None
    stop, it = "iterations", 0
    for it in range(1, iterations + 1):
        lin = linearise(x)
        cost = float(lin.cost)
        if cost0 is None:
            cost0 = cost
        accepted, step, n = False, None, 0
        for n in range(1, tries + 1):
            try:
                step = lin.solve(lam)
            except np.linalg.LinAlgError:
                lam *= singular_increase
                continue
            cand, c_new = lin.evaluate(step)
            c_new = float(c_new)
            if np.isfinite(c_new) and c_new < cost:
                accepted = True
                break
            lam *= increase
        if accepted:
            drop, x, cost = cost - c_new, cand, c_new
            lam = max(lam / decrease, min_damping)
        record = dict(iteration=it, cost=cost, damping=lam, accepted=accepted, tries=n)
        log.append(record)
        if callback is not None:
            callback(x, record)
        if not accepted:
            stop = "no decrease"
            break
        if drop <= rtol * abs(cost + drop) or drop <= rtol_initial * abs(cost0):
            stop = "small decrease"
            break
        if step_size is not None and step_size(step) < step_tol:
            stop = "small step"
            break
    return Result(x, cost0, cost, it, stop, tuple(log))
