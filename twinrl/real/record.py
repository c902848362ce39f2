"""Recording episodes on a real twin: the one routine every recorder uses.

``twinrl collect``, ``twinrl.real2sim.sysid.collect``, the loops' round 0 and their deployments
all run episodes on a real twin (a gymnasium env: ``RealTwin`` or ``TwinClient``) with a policy
and record them. ``record_episodes`` is that loop, written once: each episode ``e`` is reset with
the seed ``reset_seed(e)``, driven by ``policy(e)``, a ``policy(obs, t) -> action`` made for it
(an open-loop excitation, a closed-loop one, a trained policy), and every transition goes to the
dataset ``writer`` as it happens (with the twin camera's frames when ``images``), so a process
killed mid-episode loses nothing recorded.

Seeding is the caller's, because each caller's episodes are fixed by what it promises: the loops
seed episode ``e`` from ``(seed, e)`` so a resumed run re-records exactly the episodes an
uninterrupted one would have; ``twinrl collect`` from ``(seed, the episode's id in the
dataset)`` so re-running it on the same directory appends new episodes; ``sysid.collect`` from
one generator for its episodes in turn. ``episode_seeds(seed, e)`` is the scheme new callers
should use: a reset seed and a generator for the episode's own randomness, both functions of
``(seed, e)`` alone.
"""

from __future__ import annotations

from typing import Any, Callable, Iterable, NamedTuple

import numpy as np

__all__ = ["Recorded", "record_episodes", "record_from", "episode_seeds"]


class Recorded(NamedTuple):
    """One recorded episode."""

    episode: int
    """The caller's index of the episode (what ``reset_seed`` and ``policy`` were given)."""
    ret: float
    """The episode's return."""
    steps: int
    transitions: dict[str, np.ndarray] | None
    """With ``keep``: ``obs``, ``action``, ``next_obs``, ``reward`` (one row per step)."""


def episode_seeds(seed: int, e: int) -> tuple[int, np.random.Generator]:
    """Episode ``e``'s reset seed and random generator from ``(seed, e)`` alone (the
    ``SeedSequence`` of ``[seed, e]``: its first word, and a generator of its first child)."""
    seq = np.random.SeedSequence([int(seed), int(e)])
    return int(seq.generate_state(1)[0]), np.random.default_rng(seq.spawn(1)[0])


def record_episodes(twin, episodes: Iterable[int], policy: Callable[[int], Callable],
                    reset_seed: Callable[[int], int], *, writer=None, images: bool = False,
                    steps: int | None = None, keep: bool = False,
                    after_reset: Callable[[int], Any] | None = None,
                    on_episode: Callable[[Recorded], Any] | None = None) -> list[Recorded]:
    """Run and record the ``episodes`` (an iterable of indices ``e``, in order) on ``twin``.

    Episode ``e``: ``twin.reset(seed=reset_seed(e))``, then ``after_reset(e)`` if given (e.g. a
    camera move before the first step), then ``policy(e)``'s actions ``act(obs, t)`` (asked for
    once per episode, after the reset, so a policy drawing from a shared generator draws in
    episode order) until the episode ends, or for ``steps`` steps when given (the last one
    recorded as truncated; the twin's own truncation then does not stop it). Every transition
    goes to ``writer`` (a ``twinrl.real.dataset.DatasetWriter``, optional) with the step's scalar
    ``info`` and, with ``images``, the RGB, depth and segmentation of the twin's camera.
    ``on_episode`` gets each ``Recorded`` as it ends. Returns them all."""
    if steps is not None and int(steps) < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    done_list = []
    for e in episodes:
        obs, _ = twin.reset(seed=int(reset_seed(e)))
        if after_reset is not None:
            after_reset(e)
        ret, t, rows = record_from(twin, policy(e), obs, writer=writer, images=images,
                                   steps=steps, keep=keep)
        rec = Recorded(e, ret, t, rows)
        done_list.append(rec)
        if on_episode is not None:
            on_episode(rec)
    return done_list


def record_from(twin, act: Callable, obs, *, writer=None, images: bool = False,
                steps: int | None = None, keep: bool = False):
    """One episode of ``act(obs, t) -> action`` on ``twin`` from ``obs`` (what its last
    ``reset`` returned), recorded as ``record_episodes`` records (see there for ``steps``,
    ``writer``, ``images``). Returns ``(return, steps, transitions or None)``."""
    from twinrl.render.opengl import IMAGE_KINDS

    rows: dict[str, list] = {k: [] for k in ("obs", "action", "next_obs", "reward")}
    ret, t, done = 0.0, 0, False
    while not done:
        a = np.asarray(act(obs, t), np.float32)
        nxt, r, term, trunc, info = twin.step(a)
        last = steps is not None and t == int(steps) - 1
        if writer is not None:
            frames = twin.render_images(twin.camera, IMAGE_KINDS) if images else None
            writer.add(obs, a, r, nxt, term, trunc or last,
                       info={k: v for k, v in info.items() if np.isscalar(v)}, images=frames)
        if keep:
            for k, v in zip(rows, (obs, a, nxt, r)):
                rows[k].append(v)
        obs, ret, t = nxt, ret + float(r), t + 1
        done = bool(term) or (last if steps is not None else bool(trunc))
    return ret, t, ({k: np.asarray(v) for k, v in rows.items()} if keep else None)
