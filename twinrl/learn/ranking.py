"""How well a sensing Q ranks camera poses (``twinrl.learn.sensing``, ``bench/q_rank.py``).

A camera choice needs Q to order the poses of one start state as the actor's outcome from them
does; a state's own difficulty does not matter to it. ``rank_corr_per_state`` is Spearman's
correlation across the poses of each state, ``evaluate_ranking`` the held-out figures the
sensing stage reports. ``sensing`` re-exports both."""

from __future__ import annotations

import numpy as np

from twinrl.learn.camera_choice import q_predictions
from twinrl.learn.networks import Network

__all__ = ["rank_corr_per_state", "evaluate_ranking"]


def _rank_corr(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman's rank correlation of two vectors, ties at their mean rank (0 when either is
    constant)."""
    from scipy.stats import rankdata

    if np.ptp(a) == 0 or np.ptp(b) == 0:
        return 0.0
    ra, rb = rankdata(a), rankdata(b)
    return float(np.corrcoef(ra, rb)[0, 1])


def rank_corr_per_state(pred: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Spearman's correlation of Q (``pred``, ``q_predictions``) with the target across the
    poses of each start state, at the episodes' first example: (S,)."""
    return np.asarray([_rank_corr(p, t) for p, t in zip(pred[:, :, 0], target[:, :, 0])])


def evaluate_ranking(q: Network, q_params, data, pred=None) -> dict:
    """On held-out data (a ``sensing.SensingData``): Q's loss, its per-state rank correlation
    with the target across poses (first example of each episode; ``rank_corr``, what a camera
    choice needs) and over all the held-out (state, pose) pairs (``rank_corr_pooled``: a state's
    own difficulty counts too), the target at Q's preferred pose vs the poses' mean and best,
    and the episode return from Q's preferred pose (``return``). ``pred``: ``q_predictions`` of
    ``data``, if computed."""
    pred = q_predictions(q, q_params, data) if pred is None else np.asarray(pred)
    target = np.asarray(data.targets)
    first_pred, first_target = pred[:, :, 0], target[:, :, 0]
    corr = rank_corr_per_state(pred, target)
    pick = np.argmax(first_pred, axis=1)
    rows = np.arange(len(pick))
    return {"val_loss": float(np.mean((pred - target) ** 2)),
            "rank_corr": float(np.mean(corr)),
            "rank_corr_pooled": _rank_corr(first_pred.ravel(), first_target.ravel()),
            "target_q_choice": float(np.mean(first_target[rows, pick])),
            "target_mean_pose": float(np.mean(first_target)),
            "target_best_pose": float(np.mean(first_target.max(axis=1))),
            "success_q_choice": float(np.mean(np.asarray(data.success)[rows, pick])),
            "success_mean_pose": float(np.mean(np.asarray(data.success))),
            "return": float(np.mean(np.asarray(data.returns)[rows, pick]))}
