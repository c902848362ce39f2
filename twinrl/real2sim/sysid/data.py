"""The data sysid fits: excitation of the real twin and multiple-shooting windows of a dataset.

``excitation_actions``/``collect`` record safe, exciting open-loop episodes on a real twin;
``windows_from_dataset`` cuts recorded episodes into the short shooting windows of the fit (Bock &
Plitt 1984; ``twinrl.real2sim.sysid``, "Multiple shooting"), with the actions each window's system
executed under a given latency.
"""

from __future__ import annotations

import os
from typing import Mapping, NamedTuple

import jax
import numpy as np

from twinrl.envs.base import Env
from twinrl.envs.registry import TASKS
from twinrl.real.record import record_episodes

__all__ = ["excitation_actions", "collect", "Windows", "windows_from_dataset"]


def excitation_actions(rng: np.random.Generator | int, T: int, m: int, *,
                       hold: tuple[int, int] = (3, 15), amplitude: float = 1.0) -> np.ndarray:
    """Random actions with persistence: levels uniform in [-amplitude, amplitude], each held for
    a random number of steps in ``hold`` (inclusive). Shape (T, m), float32.

    Persistence excites a mechanical system far better than i.i.d. noise, whose high frequencies
    the inertia filters out: held forces build up the velocities that make damping and friction
    visible, and their switches make the mass and gain visible. The safe initial policy of the
    loop's round 0.
    """
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    lo, hi = int(hold[0]), int(hold[1])
    if T < 0 or m < 1 or not 1 <= lo <= hi:
        raise ValueError(f"excitation_actions needs T >= 0, m >= 1, 1 <= hold[0] <= hold[1]; "
                         f"got T={T}, m={m}, hold={hold}")
    out = np.empty((T, m), np.float32)
    for j in range(m):
        t = 0
        while t < T:
            n = int(rng.integers(lo, hi + 1))
            out[t:t + n, j] = rng.uniform(-amplitude, amplitude)
            t += n
    return out


def collect(twin, episodes: int, seed: int = 0, *, steps: int | None = None,
            writer=None, policy="auto", **excitation) -> dict[str, np.ndarray]:
    """Run an excitation on a real twin (a gymnasium env) for ``episodes``.

    ``policy``: ``"open_loop"``, ``excitation_actions`` (``excitation`` are its keyword
    arguments); ``"task"``, the task's closed-loop ``excitation_policy(rng)`` (push has one: open
    loop rarely touches its box); ``"auto"`` (default), the task's where it has one; or your own
    closed-loop excitation, a callable ``make(rng) -> policy(obs, t) -> action`` (the
    contract of ``excitation_policy``), e.g. one designed for the parameters you identify.
    Returns ``{"obs", "action", "next_obs", "reward"}`` with shapes (E, T, ...); if ``writer``
    (a ``twinrl.real.dataset.DatasetWriter``) is given, every transition is also recorded there
    (``twinrl.real.record.record_episodes``, with each step's scalar ``info``). Episode ``ep``
    resets with seed ``1000 * seed + ep``; its actions draw from one generator seeded ``seed``.
    """
    if int(episodes) < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if steps is not None and int(steps) < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    custom = callable(policy)
    if not custom and policy not in ("auto", "open_loop", "task"):
        raise ValueError(f"policy must be 'auto', 'open_loop', 'task' or a callable "
                         f"make(rng) -> policy(obs, t), got {policy!r}")
    task_policy = policy if custom else getattr(twin.task, "excitation_policy", None)
    if policy == "task" and task_policy is None:
        raise ValueError(f"task {twin.task.name!r} has no excitation_policy; use "
                         f"policy='open_loop'")
    closed = task_policy is not None and policy != "open_loop"
    rng = np.random.default_rng(seed)
    T = int(steps or twin.task.episode_length)
    m = int(twin.action_space.shape[0])

    def make(ep):  # drawn from the one generator, episode after episode
        if closed:
            return task_policy(rng)
        acts = excitation_actions(rng, T, m, **excitation)
        return lambda o, t: acts[t]

    recorded = record_episodes(twin, range(int(episodes)), make,
                               lambda ep: int(seed) * 1000 + ep, writer=writer, steps=T,
                               keep=True)
    out = {k: [r.transitions[k] for r in recorded] for k in ("obs", "action", "next_obs",
                                                              "reward")}
    lengths = {len(x) for x in out["reward"]}
    if len(lengths) != 1:  # an episode terminated early (diverged): keep ragged as a list
        return {k: list(v) for k, v in out.items()}
    return {k: np.stack(v) for k, v in out.items()}


class Windows(NamedTuple):
    """Shooting windows cut from recorded episodes (n windows of W steps)."""

    qpos0: np.ndarray
    """(n, nq) state each window starts from (``Env.state_from_obs`` of its first obs)."""
    qvel0: np.ndarray
    """(n, nv)."""
    actions: np.ndarray
    """(n, max_latency + W, nu) actions sent at steps t0 - max_latency .. t0 + W - 1 (zeros
    before the episode began)."""
    obs0: np.ndarray
    """(n, obs_size) recorded observation at each window's start."""
    targets: np.ndarray
    """(n, W, obs_size) recorded next observations."""
    episode: np.ndarray
    """(n,) index of the episode (in the order given) each window comes from."""
    start: np.ndarray
    """(n,) step within the episode at which each window starts."""
    max_latency: int

    def select(self, keep) -> "Windows":
        """The windows ``keep`` picks: a boolean mask (n,) or indices. E.g. a first fit of a
        robot's own parameters on the windows where it touches nothing (``Push.pusher_clear``),
        before the object's parameters on all of them."""
        n = len(self.qpos0)
        k = np.asarray(keep)
        if k.dtype == bool:
            if k.shape != (n,):
                raise ValueError(f"Windows.select: a mask needs shape ({n},), got {k.shape}")
            k = np.flatnonzero(k)
        elif k.size and (k.ndim != 1 or not np.issubdtype(k.dtype, np.integer)
                         or k.min() < -n or k.max() >= n):
            raise ValueError(f"Windows.select: give a boolean mask ({n},) or indices in "
                             f"[-{n}, {n}), got {keep!r}")
        if k.size == 0:
            raise ValueError(f"Windows.select keeps none of the {n} windows")
        return Windows(*(getattr(self, f)[k] for f in Windows._fields[:-1]), self.max_latency)


def _episodes_of(data) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    """``(label, obs, action, next_obs)`` per episode from a Dataset, a mapping or a list."""
    if hasattr(data, "episodes") and hasattr(data, "episode_starts"):  # twinrl.real.dataset
        out = []
        for ep in data.episodes():
            step = np.asarray(ep.step)
            if len(step) and not np.array_equal(step, np.arange(step[0], step[0] + len(step))):
                gap = int(np.flatnonzero(np.diff(step) != 1)[0])
                raise ValueError(f"episode {ep.id}: steps are not contiguous (step {step[gap]} is "
                                 f"followed by {step[gap + 1]}): records were lost there")
            out.append((f"episode {ep.id}", ep.obs, ep.action, ep.next_obs))
        return out
    if isinstance(data, Mapping):
        missing = [k for k in ("obs", "action", "next_obs") if k not in data]
        if missing:
            raise ValueError(f"data is missing {', '.join(missing)}; give obs, action, next_obs "
                             "arrays (T, dim) or (episodes, T, dim), or a twinrl Dataset")
        obs, act, nxt = data["obs"], data["action"], data["next_obs"]
        if isinstance(obs, (list, tuple)):
            return [(f"episode {i}", o, a, n) for i, (o, a, n) in enumerate(zip(obs, act, nxt))]
        obs, act, nxt = np.asarray(obs), np.asarray(act), np.asarray(nxt)
        if obs.ndim == 3:
            if not (act.ndim == 3 and nxt.ndim == 3):
                raise ValueError(f"data: obs is (episodes, T, dim) {obs.shape} but action is "
                                 f"{act.shape} and next_obs {nxt.shape}")
            return [(f"episode {i}", obs[i], act[i], nxt[i]) for i in range(obs.shape[0])]
        return [("episode 0", obs, act, nxt)]
    if isinstance(data, (list, tuple)):
        return [(f"episode {i}", e["obs"], e["action"], e["next_obs"]) for i, e in enumerate(data)]
    raise TypeError(f"data must be a twinrl.real.dataset.Dataset (or its path), a mapping of "
                    f"arrays or a list of episodes, got {type(data).__name__}")


def windows_from_dataset(env: Env, data, window: int, stride: int | None = None,
                         max_latency: int = 0) -> Windows:
    """Cut every episode of ``data`` into shooting windows of ``window`` steps.

    ``data``: a ``twinrl.real.dataset.Dataset`` (``twinrl.real.dataset.read(path)``, or the
    path itself), a mapping with ``obs``, ``action``, ``next_obs`` arrays of shape (T, dim) or
    (E, T, dim) (or lists of per-episode arrays), or a list of such per-episode mappings.
    Raises ``ValueError`` naming the episode and step of a NaN/inf, a dimension that does not
    match ``env``, or an episode shorter than ``window``.
    """
    window, stride = int(window), int(stride or window)
    if window < 1 or stride < 1:
        raise ValueError(f"window and stride must be >= 1, got {window}, {stride}")
    if isinstance(data, (str, os.PathLike)):
        from twinrl.real.dataset import read

        data = read(data)
    meta_env = getattr(data, "meta", {}).get("env") if hasattr(data, "meta") else None
    if meta_env and meta_env != env.name:
        from twinrl.envs import TASKS
        if meta_env not in TASKS or TASKS[meta_env].env_class.scene != env.scene:
            raise ValueError(f"the dataset was recorded on {meta_env!r}, a different system "
                             f"from {env.name!r} (scene {env.scene!r})")
    o_dim, a_dim = env.observation_size, env.action_size
    episodes = _episodes_of(data)
    if not episodes:
        raise ValueError("data holds no episodes")
    to_state = jax.jit(env.state_from_obs)
    cols = {k: [] for k in Windows._fields if k != "max_latency"}
    for i, (label, obs, act, nxt) in enumerate(episodes):
        obs, act, nxt = (np.asarray(x, np.float64) for x in (obs, act, nxt))
        if act.ndim == 1 and a_dim == 1:
            act = act[:, None]
        for nm, x, d in (("obs", obs, o_dim), ("action", act, a_dim), ("next_obs", nxt, o_dim)):
            if x.ndim != 2 or x.shape[1] != d:
                raise ValueError(f"{label}: {nm} has shape {x.shape}; {env.name} needs (T, {d})")
        if not (len(obs) == len(act) == len(nxt)):
            raise ValueError(f"{label}: obs, action and next_obs have different lengths "
                             f"{len(obs)}, {len(act)}, {len(nxt)}")
        for nm, x in (("obs", obs), ("action", act), ("next_obs", nxt)):
            bad = ~np.isfinite(x)
            if bad.any():
                t, j = (int(v) for v in np.argwhere(bad)[0])
                raise ValueError(f"{label}: {nm}[{t}, {j}] is {x[t, j]} (NaN/inf); drop or "
                                 "repair that step before sysid")
        T = len(obs)
        if T < window:
            raise ValueError(f"{label} has {T} steps, shorter than the shooting window of "
                             f"{window}; use a shorter window or drop the episode")
        starts = np.arange(0, T - window + 1, stride)
        qpos, qvel = (np.asarray(x, np.float64) for x in to_state(obs[starts]))
        padded = np.concatenate([np.zeros((max_latency, a_dim)), act])
        cols["qpos0"].append(qpos)
        cols["qvel0"].append(qvel)
        cols["actions"].append(np.stack([padded[s:s + max_latency + window] for s in starts]))
        cols["obs0"].append(obs[starts])
        cols["targets"].append(np.stack([nxt[s:s + window] for s in starts]))
        cols["episode"].append(np.full(len(starts), i))
        cols["start"].append(starts)
    return Windows(**{k: np.concatenate(v) for k, v in cols.items()},
                   max_latency=int(max_latency))
