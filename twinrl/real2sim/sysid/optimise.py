"""The optimisers of sysid: Levenberg-Marquardt (iteratively reweighted Gauss-Newton with
Marquardt damping, on the Jacobian from forward-mode AD; the damping loop is
``twinrl.real2sim.lm``'s, shared with visual Real2Sim) and Adam, on a ``Problem``
(``twinrl.real2sim.sysid``, "Levenberg-Marquardt"). ``normal_terms`` are the Gauss-Newton
normal equations of the robust loss, shared with the Laplace approximation.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import optax

from twinrl.real2sim.lm import Linearisation, minimise
from twinrl.real2sim.sysid.problem import Problem, rho

__all__ = ["normal_terms", "levenberg_marquardt", "adam_fit"]


def _objective(prob: Problem, r: np.ndarray, theta, kappa: float, offset=None) -> float:
    out = prob.data_loss(r) + kappa * prob.prior(theta)
    if offset is not None:  # the estimated start states' prior around the recorded ones
        out += 0.5 * kappa * float(np.sum(offset * offset)) / prob.config.start_prior_sd ** 2
    return out


def normal_terms(r, J, Jx, w, fi):
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


def levenberg_marquardt(prob: Problem, theta, latency: int, free: np.ndarray, log,
                        start: bool) -> np.ndarray:
    """Levenberg-Marquardt with IRLS weights for the robust loss and the Gaussian prior; with
    ``start``, every window's start state is estimated too (in tangent coordinates, with a weak
    prior around the recorded state; eliminated per window by the Schur complement, as in bundle
    adjustment), and ``prob.qpos0/qvel0`` are updated. The damping
    schedule and stopping rule are ``twinrl.real2sim.lm.minimise``'s; this builds and solves the
    damped normal equations. ``log(theta, mean data loss)`` is called after every iteration."""
    c = prob.config
    nv = prob.sim.nv
    fi = np.flatnonzero(free)
    kept = {}  # residuals at the current point and at the last candidate (for ``log``)

    def linearise(x):
        theta, q, v = x
        prob.qpos0, prob.qvel0 = q, v
        r, J, Jx = prob.jacobian(theta, latency, start=True) if start else (
            *prob.jacobian(theta, latency), None)
        offset = prob.start_offset(q, v) if start else None
        kept["r"] = r
        # The prior is worth one residual's mean loss per parameter at the current fit (about one
        # unit of -2 log-likelihood per prior sd^2): negligible against thousands of residuals,
        # decisive only along flat directions. Weighed at the starting loss instead, it kept that
        # weight while the loss fell 100-fold and held a zero friction loss at a positive value.
        kappa = 2.0 * prob.data_loss(r) / r.size + 1e-12
        prior_prec = kappa / c.prior_sd ** 2
        _, w = rho(r, c.loss, c.loss_scale)
        Htt, gt, Htx, Hxx, gx, _ = normal_terms(r, J, Jx, w, fi)
        Htt = Htt + prior_prec * np.eye(len(fi))
        gt = gt + prior_prec * (theta[fi] - prob.theta0[fi])
        if start:
            # The same prior on each start state, around its recorded value, in tangent
            # coordinates: decisive only where the data say nothing (a disc's spin about its
            # axis). Without it Marquardt's damping, relative to a zero diagonal, left such
            # directions free: steps of 1e5 rad/s, a blown-up rollout, the damping raised until
            # the parameters barely moved (spatula: 14 servo parameters stuck at nominal).
            x_prec = kappa / c.start_prior_sd ** 2
            Hxx = Hxx + x_prec * np.eye(Hxx.shape[-1])
            gx = gx + x_prec * offset

        def solve(lam):
            A = Htt + lam * np.diag(np.maximum(np.diag(Htt), 1e-12))
            if Jx is None:
                return -np.linalg.solve(A, gt), None
            Ax = Hxx + lam * np.einsum("nk,kl->nkl", np.maximum(
                np.einsum("nkk->nk", Hxx), 1e-12), np.eye(Hxx.shape[-1]))
            Ai = np.linalg.inv(Ax)
            S = A - np.einsum("npk,nkl,nql->pq", Htx, Ai, Htx)
            rhs = gt - np.einsum("npk,nkl,nl->p", Htx, Ai, gx)
            dt = -np.linalg.solve(S, rhs)
            return dt, -np.einsum("nkl,nl->nk", Ai, gx + np.einsum("npl,p->nl", Htx, dt))

        def evaluate(step):
            dt, dx = step
            cand = theta.copy()
            cand[fi] += dt
            qc, vc = (q, v) if dx is None else (prob.retract(q, dx[:, :nv]), v + dx[:, nv:])
            rc = kept["cand"] = prob.residuals(cand, latency, qc, vc)
            oc = (_objective(prob, rc, cand, kappa, None if dx is None else
                             prob.start_offset(qc, vc)) if np.all(np.isfinite(rc)) else np.inf)
            return (cand, qc, vc), oc

        return Linearisation(_objective(prob, r, theta, kappa, offset), solve, evaluate)

    def on_iteration(x, record):
        if record["accepted"]:
            kept["r"] = kept["cand"]
        log(x[0], prob.data_loss(kept["r"]) / kept["r"].size)

    x0 = (np.array(theta, np.float64), prob.qpos0.copy(), prob.qvel0.copy())
    res = minimise(linearise, x0, damping=c.lm_damping, iterations=c.lm_steps, tries=12,
                   rtol=c.tol, step_tol=c.step_tol,
                   step_size=lambda step: float(np.max(np.abs(step[0]), initial=0.0)),
                   callback=on_iteration)
    theta, prob.qpos0, prob.qvel0 = res.x
    return theta


def adam_fit(prob: Problem, theta, latency: int, log) -> np.ndarray:
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
