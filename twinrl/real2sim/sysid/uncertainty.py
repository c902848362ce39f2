"""Uncertainty and identifiability of a sysid fit (``twinrl.real2sim.sysid``, "Uncertainty",
"Identifiability", "Parameters at their bound 0").

``laplace``: the posterior covariance by the Laplace / Gauss-Newton approximation (window-clustered
sandwich by default), its flat eigen-directions and each parameter's status; ``bound_tests``: the
likelihood-ratio test of holding each non-negative parameter at its bound 0.
"""

from __future__ import annotations

import math

import numpy as np

from twinrl.physics.params import NONNEGATIVE
from twinrl.real2sim.sysid.optimise import levenberg_marquardt, normal_terms
from twinrl.real2sim.sysid.problem import (Problem, dvalue_du, from_unconstrained, rho,
                                           to_unconstrained)

__all__ = ["bound_tests", "laplace", "BOUND_SCREEN"]

BOUND_SCREEN = 100.0
"""Standard deviations from 0 beyond which ``bound_tests`` does not refit a parameter at 0. A
refit is a whole fit: a 7-joint Panda's dampings (24-61 N s/m) cost 1,259 of a 1,328 s
identification in seven refits whose likelihood ratios were 3e9 to 6e13 against a threshold of
2.71 (``bench/sysid_baseline.py``); at 100 sd the quadratic approximation says 1e4."""


def bound_tests(prob: Problem, theta, latency: int, free: np.ndarray, start: bool, info: dict,
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
    A candidate further than ``BOUND_SCREEN`` standard deviations from 0 is not refitted: its
    entry is the Wald statistic ``z^2``, the likelihood ratio's quadratic approximation, and it
    and every candidate after it (further still) stay free.
    Returns the new ``theta``, ``free``, the bound indices, their ``laplace`` info and the
    scaled likelihood ratio of each tested parameter (by name)."""
    c = prob.config
    cand = [int(j) for j in np.flatnonzero(free) if prob.spec[j][0] in NONNEGATIVE]
    if not cand:
        return theta, free, [], info, {}
    var = info["var"]

    def deviance(r):
        return 2.0 * float(np.sum(rho(r, c.loss, c.loss_scale)[0].sum(axis=(0, 1)) / var))

    def z(j):
        f = prob.spec[j][0]
        return from_unconstrained(f, theta[j]) / max(dvalue_du(f, theta[j]) * info["sd_u"][j],
                                                     1e-300)

    d_cur = deviance(prob.residuals(theta, latency))
    bound: list[int] = []
    tests = {}
    for j in sorted(cand, key=z):
        if z(j) > BOUND_SCREEN:
            tests[prob.names[j]] = float(z(j)) ** 2
            continue
        q, v = prob.qpos0.copy(), prob.qvel0.copy()
        trial_free = free.copy()
        trial_free[j] = False
        th = theta.copy()
        th[j] = to_unconstrained(prob.spec[j][0], 0.0)
        if trial_free.any():
            th = levenberg_marquardt(prob, th, latency, trial_free, lambda *_: None, start)
        r = prob.residuals(th, latency)
        d = deviance(r)
        trial = laplace(prob, th, latency, trial_free, start, bound=bound + [j])
        tests[prob.names[j]] = lr = (d - d_cur) * float(trial["gn_ratio"][j])
        if lr < c.bound_lr:
            theta, free, d_cur, info = th, trial_free, d, trial
            bound.append(j)
            log(theta, prob.data_loss(r) / r.size)
        else:
            prob.qpos0, prob.qvel0 = q, v
    return theta, free, bound, info, tests


def laplace(prob: Problem, theta, latency: int, free: np.ndarray, start: bool, extra_flat=(),
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
    dv[nf:] = [dvalue_du(prob.spec[j][0], theta[j]) for j in bound]
    J = J[..., idx] / dv
    cols = np.arange(len(idx))
    _, w = rho(r, c.loss, c.loss_scale)
    # Residual variance per observation dimension (robust: the IRLS-weighted mean square).
    n_x = 0 if Jx is None else n * Jx.shape[-1]
    dof = max(r.size - len(idx) - n_x, 1)
    var = np.maximum(np.sum(w * r * r, axis=(0, 1)) / (dof / o), 1e-300)
    wt = w / var
    F, _, Htx, Hxx, _, g = normal_terms(r, J, Jx, wt, cols)
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
