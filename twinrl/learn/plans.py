"""Demonstrations by trajectory optimisation: optimised action sequences from random starts of a
task, the expert that ``twinrl.learn.imitation`` clones (SAM-RL's "optimised trajectories").

``plan(env, starts, ...)`` runs ``twinrl.learn.trajopt`` (first order with a line search) from
``starts`` reset keys, ``batch`` at a time (vmap), from zero actions; the starts it did not solve
are re-optimised up to ``restarts`` more times, each from the next of ``initial_guesses`` (for an
arm task with an ``approach_point``: the straight-line approach, the approach stopping 2 cm short,
smooth random actions; for others random actions). ``save``/``imitation.load_demonstrations``
write and read ``<task>_plans.npz``: ``actions`` (N, T, m), ``keys`` (N, 2) and ``success`` (N,).

Used by ``bench/manipulation.py`` (the suite's trajopt figures) and by the manipulation loop's
``plan`` stage (``twinrl.loop.arm``), which plans in the identified twin.
"""

from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.learn import trajopt

__all__ = ["Demonstrations", "DemonstrationError", "load_demonstrations", "initial_guesses",
           "plan", "relabel", "save", "smooth_noise", "solves"]


class DemonstrationError(ValueError):
    """Missing, malformed or mismatched demonstrations (the CLI prints it as one line)."""


class Demonstrations(NamedTuple):
    keys: np.ndarray
    """(N, 2) uint32 reset keys of the start states."""
    actions: np.ndarray
    """(N, T, m) the optimised action sequences."""


def load_demonstrations(path: str | Path, successful_only: bool = True) -> Demonstrations:
    """Demonstrations from a ``<task>_plans.npz`` (``save``): ``keys``,
    ``actions`` and ``success``; only the successful plans unless ``successful_only=False``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no demonstration file {path}")
    with np.load(path) as z:
        missing = {"keys", "actions"} - set(z.files)
        if missing:
            raise DemonstrationError(f"{path} is not a demonstration file: no {sorted(missing)}")
        keys, actions = np.asarray(z["keys"]), np.asarray(z["actions"], np.float32)
        keep = (np.asarray(z["success"]) > 0 if successful_only and "success" in z.files
                else np.ones(len(keys), bool))
    if not keep.any():
        raise DemonstrationError(f"{path} holds no successful demonstration")
    return Demonstrations(keys[keep], actions[keep])


def smooth_noise(key, shape, knots: int = 6, scale: float = 0.15):
    """Smooth random actions: ``scale``-sd values at ``knots`` evenly spread steps, linearly
    interpolated over the horizon."""
    T = shape[-2]
    z = scale * jax.random.normal(key, shape[:-2] + (knots, shape[-1]))
    t = jnp.linspace(0.0, knots - 1.0, T)
    interp = lambda c: jnp.interp(t, jnp.arange(knots, dtype=t.dtype), c)  # noqa: E731
    return jnp.clip(jnp.vectorize(interp, signature="(k)->(t)")(
        jnp.swapaxes(z, -1, -2)).swapaxes(-1, -2), -1.0, 1.0)


def initial_guesses(env, restarts: int) -> list[str]:
    """The initial action sequence of each attempt: zeros first; then, for a task with an
    ``approach_point`` (``ArmTask.approach_plan``), the straight-line approach, the approach
    stopping 2 cm short, and smooth random actions; for the others random actions
    (N(0, 0.3^2), clipped) -- a local method's usual remedies for a poor local optimum, most
    structured first."""
    has_approach = (hasattr(env, "approach_point") and env.approach_point(
        env.reset(jax.random.PRNGKey(0)).pipeline_state.qpos) is not None)
    later = ["approach", "approach-2cm", "smooth"] if has_approach else ["random"]
    return ["zero"] + [later[min(i, len(later) - 1)] for i in range(restarts)]


def plan(env, starts: int, iterations: int = 20, batch: int = 10, seed: int = 0,
         config: trajopt.TrajoptConfig | None = None, restarts: int = 2,
         say: Callable[[str], None] | None = None, keys=None) -> dict:
    """Trajectory optimisation of ``env`` from ``starts`` random initial states (reset keys split
    from ``seed``; or from ``reset(keys[i])``, ``starts`` then being ``len(keys)``: chosen starts,
    a real twin's for one), ``batch`` at a time: from zero actions, then, for the starts not solved
    (``env.success`` at the episode's end), up to ``restarts`` times more from the next of
    ``initial_guesses``. ``config`` defaults to first order, step 0.5, 6 line-search steps.

    Returns the statistics (success rate, on the first attempt and in all, which attempt solved
    how many, seconds per solved start, compile seconds, initial and final mean returns) and, under
    ``plans``/``keys``/``success``, the arrays ``save`` writes."""
    if keys is not None:
        keys = jnp.asarray(keys, jnp.uint32).reshape(-1, 2)
        starts = int(keys.shape[0])
    if starts < 1 or batch < 1 or iterations < 1 or restarts < 0:
        raise ValueError(f"plan needs starts, batch, iterations >= 1 and restarts >= 0, got "
                         f"{starts}, {batch}, {iterations}, {restarts}")
    config = config or trajopt.TrajoptConfig(order=1, step_size=0.5, line_search_steps=6)
    say = say or (lambda s: None)
    T = env.episode_length
    batch = min(batch, starts)
    if keys is None:
        keys = jax.random.split(jax.random.PRNGKey(seed), starts)

    def one(key, a0):
        s = env.reset(key)
        rollout_fn, reward_fn = trajopt.env_problem(env, s)
        a, hist = trajopt.optimize(rollout_fn, reward_fn, a0, config, iterations)
        final, rewards = env.unroll(s, a)
        q, v = final.pipeline_state.qpos, final.pipeline_state.qvel
        return a, rewards.sum(), env.success(q, v), hist.value[0]

    def guess(kind, key, noise_key):
        zeros = jnp.zeros((T, env.action_size))
        if kind == "zero":
            return zeros
        if kind == "random":
            return jnp.clip(0.3 * jax.random.normal(noise_key, zeros.shape), -1.0, 1.0)
        if kind == "smooth":
            return smooth_noise(noise_key, zeros.shape)
        return env.approach_plan(env.reset(key), 0.02 if kind == "approach-2cm" else 0.0)

    kinds = initial_guesses(env, restarts)
    f = jax.jit(jax.vmap(one))
    guesses = {k: jax.jit(jax.vmap(functools.partial(guess, k))) for k in set(kinds)}
    t0 = time.perf_counter()
    f = f.lower(keys[:batch], jnp.zeros((batch, T, env.action_size))).compile()
    compile_s = time.perf_counter() - t0
    plans = np.zeros((starts, T, env.action_size), np.float32)
    returns, initial = np.full(starts, -np.inf), np.zeros(starts)
    success = np.zeros(starts)
    tries = np.zeros(starts, int)
    solved_by, first = {}, 0.0
    t0 = time.perf_counter()
    for attempt, kind in enumerate(kinds):
        todo = np.flatnonzero(success == 0)
        before = int(success.sum())
        for i in range(0, todo.size, batch):
            idx = todo[i:i + batch]
            pad = np.resize(idx, batch)  # pad the last batch to the compiled size
            noise = jax.random.split(jax.random.PRNGKey(seed + 1000 * attempt + i), batch)
            a0 = guesses[kind](keys[pad], noise)
            a, r, ok, r0 = (np.asarray(x) for x in jax.block_until_ready(f(keys[pad], a0)))
            n = idx.size
            better = (ok[:n] > success[idx]) | ((ok[:n] == success[idx]) & (r[:n] > returns[idx]))
            for j in np.flatnonzero(better):
                plans[idx[j]], returns[idx[j]], success[idx[j]] = a[j], r[j], ok[j]
            if attempt == 0:
                initial[idx] = r0[:n]
            tries[idx] += 1
            say(f"{env.name}: attempt {attempt + 1} ({kind}), {min(i + batch, todo.size)}/"
                f"{todo.size} optimised, solved {int(success.sum())}/{starts} "
                f"({time.perf_counter() - t0:.0f} s)")
        solved_by[f"{attempt + 1}:{kind}"] = int(success.sum()) - before
        if attempt == 0:
            first = float(success.mean())
        if success.all():
            break
    wall = time.perf_counter() - t0
    return {
        "starts": starts, "iterations": iterations, "restarts": restarts,
        "initial_guesses": kinds, "solved_by_attempt": solved_by,
        "trajopt_compile_s": compile_s,
        "success_rate": float(success.mean()),
        "success_rate_first_attempt": first,
        "seconds_per_solved": wall / max(1, int(success.sum())),
        "optimisations_run": int(tries.sum()),
        "return_initial_mean": float(initial.mean()),
        "return_final_mean": float(returns.mean()),
        "plans": plans, "keys": np.asarray(keys), "success": success,
    }


def save(path: str | Path, result: dict) -> Path:
    """Write ``plan``'s arrays to ``path`` (``<task>_plans.npz``: ``actions``, ``keys``,
    ``success``), atomically: a run killed while saving leaves no half-written file."""
    import os

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, actions=result["plans"], keys=result["keys"], success=result["success"])
    os.replace(tmp, path)
    return path


def solves(env, state, plan: jax.Array, steps: jax.Array | int) -> jax.Array:
    """Whether ``plan`` (T, m) from ``state`` solves the task: the task's ``success`` after
    ``steps`` of its steps (clipped to 1..T), 1.0 for a task without ``success``. Jit-able,
    ``steps`` traced."""
    if not hasattr(env, "success"):
        return jnp.ones((), jnp.float32)
    rollout_fn, _ = trajopt.env_problem(env, state)
    T = plan.shape[0]
    end = rollout_fn(plan)[jnp.clip(jnp.asarray(steps) - 1, 0, T - 1)]
    nq = env.sim.nq
    return env.success(end[:nq], end[nq:]).astype(jnp.float32)


def accurate(obs, states, env=None, tol: float = 0.005) -> jax.Array:
    """1 where a pose observation's ``"estimate"`` is within ``tol`` of the true state's in every
    entry, else 0; all 1 for other observations. Only those rows are cloned: the expert's action
    from a view whose fit went wrong (the needle's heading seen edge-on) teaches the wrong
    answer; which views give a right estimate is the sensing Q's to learn. ``env``: the truth is
    taken as the estimate is, at the identified grasp (``observe(..., nominal=False)``), not as
    the robot's nominal report ``states.obs`` (peg twin 1: 12 mm apart, nothing was cloned)."""
    if not isinstance(obs, dict) or "estimate" not in obs:
        return jnp.ones(states.reward.shape, jnp.float32)
    truth = states.obs if env is None else jax.vmap(
        lambda o: env.observe(*env.state_from_obs(o), nominal=False))(
        states.obs.reshape((-1, states.obs.shape[-1]))).reshape(states.obs.shape)
    return (jnp.max(jnp.abs(obs["estimate"] - truth), axis=-1) < tol).astype(jnp.float32)


def relabel(env, states, warm: jax.Array, config,
            steps_left: jax.Array | None = None) -> tuple[jax.Array, jax.Array]:
    """The expert's action at each of ``states`` (a batched ``State``): trajopt from the state,
    ``relabel_iterations`` first-order steps from the warm start ``warm`` (B, T, m). Returns the
    first action of each improved plan (B, m) and whether that plan solves the task (B,;
    ``solves`` after ``steps_left`` (B,) of its steps: where the episode the state came from
    ends; default all T). ``config``: an ``imitation.ImitationConfig`` (its ``step_size`` and
    ``relabel_iterations``)."""
    cfg = trajopt.TrajoptConfig(order=1, step_size=config.step_size, line_search_steps=6)
    T = warm.shape[1]
    left = jnp.full(warm.shape[:1], T) if steps_left is None else jnp.asarray(steps_left)

    def one(s, a0, n):
        a, _ = trajopt.optimize(*trajopt.env_problem(env, s), a0, cfg, config.relabel_iterations)
        return a[0], solves(env, s, a, n)

    return jax.vmap(one)(states, warm, left)
