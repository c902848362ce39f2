"""Indirect inference: remove the bias sensor noise puts into an estimator, by simulation.

A fit that starts its shooting windows from recorded states is biased when those states are noisy
(errors in variables): on ``push``, one-step windows from the real twin's states put the box's
mass 30 % high and its friction 24 % low at 1 mm of noise, 130 % / 63 % at 3.3 mm, because a
contact that opens or closes on a tenth of a millimetre turns the start's noise into a force.
No choice of residual removed it (docs/known-limits.md). Indirect inference (Gourieroux,
Monfort & Renault 1993; Smith 1993) does not need an unbiased estimator, only one whose
distribution the simulator can reproduce: run the same estimator on data *simulated* at candidate
parameters, with the same excitation, the same sensor noise and the same number of episodes, and
find the parameters at which it returns, on average, what it returned on the real data.

``indirect(estimate, simulate, data)`` solves ``mean_r E(simulate(theta, seed + r)) = E(data)`` in
log coordinates (every parameter here is positive) with ``reps`` simulated datasets per evaluation,
the same ``seed + r`` at every ``theta`` (common random numbers: the estimator's response to
``theta`` is then not drowned by a fresh draw of noise), by Broyden's method started from the
identity (its first step is the fixed point ``theta <- theta * E(data) / E(sim)``), safeguarded
against the simulated mean's noise (``min_update``). The answer is the mean of the last half of the
iterates, in log coordinates: near the root the simulated mean still scatters (a rocking box's
response is chaotic, so common random numbers decorrelate), and the iterates scatter with it.

Its uncertainty is the real dataset's own: one draw of the estimator, whose spread the simulated
draws at the answer measure, carried through the binding function's slope (``sd``: the delta
method, with the binding function's Jacobian by differences at the answer). The bias is gone;
this variance is not, and the number of real episodes sets it.

``noise_sd_from_quaternions`` estimates the sensor's noise from the data alone: a unit quaternion
observed with independent Gaussian noise of sd ``s`` on each component has norm ``1 + q.n`` to
first order, and ``q.n ~ N(0, s^2)``; on push's real twins the norms' sd is within 2 % of the
hidden noise (1.03 / 3.02 / 3.35 mm against 1.03 / 3.08 / 3.29).

``bench/push_sysid.py --indirect R`` runs it on push (the estimator: the staged one-step fit from
the recorded states; the simulator: the nominal model with the fitted pusher and the candidate
box, in MuJoCo C, through ``Perturbation.from_params``).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import mujoco
import numpy as np

__all__ = ["IndirectResult", "indirect", "noise_sd_from_quaternions"]


@dataclasses.dataclass(frozen=True)
class IndirectResult:
    values: np.ndarray
    """The de-biased parameters (the mean of the last half of the iterates, geometric)."""
    raw: np.ndarray
    """The estimator on the real data."""
    sd: np.ndarray
    """Standard deviation of ``values`` from the real data's one draw of the estimator (module
    docstring), absolute."""
    jacobian: np.ndarray
    """d log E / d log theta at the answer (k x k): by differences (``sd_step``) or Broyden's."""
    history: tuple[dict, ...]
    """Per iteration: ``theta``, the simulated estimates' geometric mean ``mean`` and their
    log-sd ``log_sd``."""

    @property
    def iterates(self) -> np.ndarray:
        return np.array([h["theta"] for h in self.history])


def indirect(estimate: Callable[[dict], np.ndarray], simulate: Callable[[np.ndarray, int], dict],
             data: dict, *, reps: int = 6, iterations: int = 6, seed: int = 100,
             raw: np.ndarray | None = None, max_step: float = 0.5, min_update: float = 0.1,
             sd_step: float | None = 0.2,
             progress: Callable[[dict], None] | None = None) -> IndirectResult:
    """De-bias ``estimate`` (a dataset -> k positive parameter values) by simulation: find ``theta``
    with ``mean_r estimate(simulate(theta, seed + r)) = estimate(data)`` (module docstring).
    ``simulate(theta, s)`` returns a dataset like ``data`` (same design, same noise) from the model
    at ``theta`` with random seed ``s``. ``raw``: ``estimate(data)`` if already computed.
    ``max_step``: the largest change of one log-parameter per iteration (a longer step is shortened,
    its direction kept). ``min_update``: Broyden's update only after a step at least this long (log
    coordinates): near the root a step is as small as the simulated mean's noise, and updates from
    such steps sent push's iteration at 3.3 mm of noise to 10x the mass in three steps; an update
    that leaves the Jacobian with an eigenvalue below 0.25 or a condition number above 100 (the
    binding function is monotone in each parameter) starts it again from the identity. ``sd_step``:
    the uncertainty's Jacobian by forward differences of this size in log coordinates at the answer,
    with the same seeds, ``(k + 1) * reps`` more estimates (Broyden's own Jacobian is right only
    along the steps it took: on a two-parameter test its off-diagonal came out 0.41 where it is 1);
    ``None``: Broyden's, for free. A difference's noise is the simulated estimates' log-sd times
    ``sqrt(2 / reps) / sd_step``: on push (log-sd 0.05 at 1 mm of noise, 0.2 at 3 mm; 6 reps) a step
    of 0.05 left entries off by 0.6 and the sd meaningless at 3 mm, hence 0.2. ``progress`` is
    called with each history entry."""
    if reps < 2 or iterations < 1:
        raise ValueError(f"indirect needs reps >= 2 and iterations >= 1, got {reps}, {iterations}")
    raw = np.asarray(estimate(data) if raw is None else raw, np.float64)
    if not np.all(np.isfinite(raw) & (raw > 0)):
        raise ValueError(f"the estimator's values on the real data are not all positive and "
                         f"finite: {raw}")
    target = np.log(raw)
    k = target.size
    x = target.copy()
    J = np.eye(k)
    history, prev = [], None

    def draw(x):
        return np.log(np.array([estimate(simulate(np.exp(x), seed + r)) for r in range(reps)],
                               np.float64))

    for it in range(iterations):
        draws = draw(x)
        mean = draws.mean(axis=0)
        f = mean - target
        if prev is not None:  # Broyden's rank-one update from the last step, if it was long
            dx, df = x - prev[0], f - prev[1]
            if np.linalg.norm(dx) > min_update:
                J = J + np.outer(df - J @ dx, dx) / float(dx @ dx)
                eig = np.linalg.eigvals(J)
                if np.min(eig.real) < 0.25 or np.linalg.cond(J) > 100:
                    J = np.eye(k)  # an update that made the binding function non-monotone
        entry = dict(iteration=it, theta=np.exp(x).tolist(), mean=np.exp(mean).tolist(),
                     log_sd=draws.std(axis=0, ddof=1).tolist(), cov=np.cov(draws.T).tolist())
        history.append(entry)
        if progress is not None:
            progress(entry)
        prev = (x, f)
        step = -np.linalg.solve(J, f)
        x = x + step * min(1.0, max_step / max(float(np.max(np.abs(step))), 1e-12))
    tail = np.log(np.array([h["theta"] for h in history[len(history) // 2:]]))
    values = np.exp(tail.mean(axis=0))
    cov = np.array(history[-1]["cov"]).reshape(k, k)
    if sd_step:
        base = draw(np.log(values))
        cov = np.cov(base.T).reshape(k, k)
        J = np.stack([(draw(np.log(values) + sd_step * np.eye(k)[j]) - base).mean(axis=0)
                      / sd_step for j in range(k)], axis=1)
    try:
        Jinv = np.linalg.inv(J)
        sd = values * np.sqrt(np.maximum(np.diag(Jinv @ cov @ Jinv.T), 0.0))
    except np.linalg.LinAlgError:
        sd = np.full(k, np.inf)
    return IndirectResult(values=values, raw=raw, sd=sd, jacobian=J,
                          history=tuple(history))


def noise_sd_from_quaternions(model: mujoco.MjModel, qpos: np.ndarray) -> float:
    """The sensor noise's sd, from recorded ``qpos`` (``(..., nq)``) of a model with free or ball
    joints: the sd of the recorded quaternions' norms about 1 (module docstring). Assumes one
    noise sd on every component, as the real twins' sensors have."""
    adr = []
    for j in range(model.njnt):
        t, a = int(model.jnt_type[j]), int(model.jnt_qposadr[j])
        if t == mujoco.mjtJoint.mjJNT_FREE:
            adr.append(a + 3)
        elif t == mujoco.mjtJoint.mjJNT_BALL:
            adr.append(a)
    if not adr:
        raise ValueError("noise_sd_from_quaternions: the model has no free or ball joint, so its "
                         "states hold no quaternion to measure the noise on")
    q = np.asarray(qpos, np.float64)
    if q.shape[-1] != model.nq:
        raise ValueError(f"noise_sd_from_quaternions: qpos has {q.shape[-1]} entries per state; "
                         f"the model has nq = {model.nq}")
    norms = np.concatenate([np.linalg.norm(q[..., a:a + 4], axis=-1).ravel() for a in adr])
    return float(np.std(norms - 1.0))
