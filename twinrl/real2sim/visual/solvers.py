"""The two optimisers of a visual fit: Adam over random restarts with an annealed silhouette
temperature (``adam_restarts``), then Levenberg-Marquardt on metric residuals
(``levenberg_marquardt``)."""

from __future__ import annotations

import functools
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax

from twinrl.jaxconfig import image_compiler_options
from twinrl.real2sim.lm import Linearisation, minimise
from twinrl.real2sim.visual.config import VisualConfig


def adam_restarts(loss_fn, params0, cfg: VisualConfig, rng: np.random.Generator, perturb):
    """Adam with a coarse-to-fine temperature over restarts; returns (best params, history)."""
    taus = np.geomspace(cfg.tau[0], cfg.tau[1], cfg.steps)
    opt = optax.adam(cfg.lr)

    @functools.partial(jax.jit, compiler_options=image_compiler_options())
    def step(p, s, tau):
        (loss, terms), g = jax.value_and_grad(loss_fn, has_aux=True)(p, tau)
        g = jax.tree_util.tree_map(lambda x: jnp.where(jnp.isfinite(x), x, 0.0), g)
        u, s = opt.update(g, s, p)
        return optax.apply_updates(p, u), s, loss, terms

    final_loss = jax.jit(loss_fn, compiler_options=image_compiler_options())
    best, runs = None, []
    for k in range(cfg.restarts):
        p = params0 if k == 0 else perturb(params0, rng)
        s = opt.init(p)
        for t in range(cfg.steps):
            p, s, loss, terms = step(p, s, taus[t])
        final, terms = final_loss(p, cfg.tau[1])
        final = float(final)
        runs.append({"restart": k, "final_loss": final,
                     **{k2: float(v) for k2, v in terms.items()}})
        if np.isfinite(final) and (best is None or final < best[1]):
            best = (p, final)
    if best is None:
        raise FloatingPointError("every restart of the visual fit diverged (non-finite loss)")
    return best[0], runs


def levenberg_marquardt(res_fn, params: dict, keys: Sequence[str], iters: int,
                         lam: float = 1e-2, starts: Sequence[dict] = ()):
    """Minimise ``0.5 |res_fn(params)|^2`` over ``params[k]`` for ``k`` in ``keys`` (the others
    held) by Levenberg-Marquardt (``twinrl.real2sim.lm.minimise``) with Marquardt's diagonal
    scaling and a forward-mode Jacobian. ``starts``: further starting values of ``keys`` (dicts
    of them), each refined as well (one compilation for all); the lowest final cost wins.
    Returns the refined params and ``{"cost_before", "cost_after", "iters"}`` of the winner,
    with ``"start"`` (0: ``params``, ``i``: ``starts[i - 1]``) and every start's final cost
    (``"costs"``) when ``starts`` are given."""
    from jax.flatten_util import ravel_pytree

    x0, unravel = ravel_pytree({k: params[k] for k in keys})

    def fun(x):
        return res_fn({**params, **unravel(x)})

    opts = image_compiler_options()  # no MJX here
    f, jac = jax.jit(fun, compiler_options=opts), jax.jit(jax.jacfwd(fun), compiler_options=opts)

    def linearise(point):  # the point carries its residuals: no re-render to linearise
        x, r = point
        J = jac(x)
        A, g = J.T @ J, J.T @ r
        D = jnp.diag(jnp.diag(A) + 1e-9 * jnp.max(jnp.diag(A)) + 1e-30)

        def evaluate(dx):
            r_new = f(x + dx)
            return (x + dx, r_new), float(0.5 * jnp.sum(r_new * r_new))

        return Linearisation(float(0.5 * jnp.sum(r * r)),
                             lambda mu: jnp.linalg.solve(A + mu * D, -g), evaluate)

    results = {}  # start index -> its minimisation
    for i, s in enumerate([None, *starts]):
        x = x0 if s is None else ravel_pytree({k: jnp.asarray(s[k], params[k].dtype)
                                               for k in keys})[0]
        r = f(x)
        if not np.isfinite(float(0.5 * jnp.sum(r * r))):
            if s is None:
                raise FloatingPointError("visual refinement: non-finite residuals at the start")
            continue  # an extra start outside where the residuals are defined: skipped
        results[i] = minimise(linearise, (x, r), damping=lam, iterations=iters, tries=10,
                              rtol_initial=1e-9)
    best = min(results, key=lambda i: results[i].cost)
    res = results[best]
    info = {"cost_before": res.cost0, "cost_after": res.cost, "iters": res.iterations}
    if starts:
        info.update(start=best, costs=[float(results[i].cost) if i in results else None
                                       for i in range(len(starts) + 1)])
    return {**params, **unravel(res.x[0])}, info
