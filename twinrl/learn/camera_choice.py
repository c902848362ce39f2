"""Choosing the camera pose with the sensing-aware Q (SAM-RL): gradient ascent of Q through the
differentiable renderer, and Q's landscape over the mount's workspace (``twinrl.sense`` draws
them for ``twinrl sense``).

``select_camera`` ascends ``J(c) = Q(o(c), pi(o(c)))`` with Adam in the mount's unconstrained
coordinates (``CameraMount``: a sigmoid keeps every pose in its workspace), the image rendered
soft (``tau``) so that the pose has a gradient through silhouettes, from the default pose and
``restarts - 1`` random ones; the winner is chosen by ``J`` on the *hard* image (the one the
actor will see) among every ``check_every``-th iterate of every ascent, its start and end
included. The ``smooth_top`` best of them and the default pose are then scored by the hard
image's Q averaged over ``smooth_samples`` poses around each (Gaussian, ``smooth_sd`` in mount
coordinates): the maximum of many noisy estimates is partly their noise (the winner's curse), and
the real camera lands off the commanded pose by the hand-eye error. The choice is never worse, by
its score, than the default pose. (For an actor on the
target's fitted pose, ``J`` reaches the pose through ``ArmTask.fit_target_pose``, whose
derivative is its converged fit's.) Q and its training live in ``twinrl.learn.sensing``.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from twinrl.learn.common import held_episodes
from twinrl.learn.networks import Network

__all__ = ["Selection", "uniform_coords", "observer", "observed_keys", "image_size", "q_value",
           "neighbourhood_offsets", "score_around", "select_camera", "checked_steps",
           "workspace_grid", "landscape", "view_outcomes", "q_predictions", "CameraCheck",
           "check_choice"]


EDGE = float(np.log(0.98 / 0.02))
"""The largest unconstrained mount coordinate drawn (``uniform_coords``) or ascended to."""


def uniform_coords(mount, key, shape=()) -> jax.Array:
    """Unconstrained mount coordinates of poses uniform over its (azimuth, elevation, distance)
    box (kept 2 % inside its edges, where the sigmoid's slope vanishes)."""
    u = jax.random.uniform(key, shape + (3,), minval=0.02, maxval=0.98)
    return jnp.log(u) - jnp.log1p(-u)


def observer(env, image_size: int, tau: float = 0.0, keys=None) -> Callable:
    """``observe(state, coords)``: the image actor's observation (``ArmTask.image_observation``),
    soft in the pose when ``tau > 0``."""
    keys = None if keys is None else tuple(keys)  # only what the networks read is traced
    return lambda s, coords: env.image_observation(s, coords, size=int(image_size), tau=tau,
                                                   keys=keys)


def observed_keys(actor: Network, q: Network) -> tuple[str, ...]:
    """The observation keys the actor and Q read (Q's ``"action"`` is the actor's output)."""
    return tuple(sorted((set(actor.obs_spec) | set(q.obs_spec)) - {"action"}))


def image_size(env, actor: Network) -> int:
    """The mount image size an image actor sees: its ``pixels/mount`` key's, or for an actor
    that reads only the image's target cloud (``"target"``), the task's ``image_size``."""
    spec = actor.obs_spec
    if isinstance(spec, dict) and "pixels/mount" in spec:
        return int(spec["pixels/mount"][0])
    return int(env.config.image_size)


def q_value(q: Network, q_params, obs: dict, action: jax.Array) -> jax.Array:
    return q.apply(q_params, {**obs, "action": action})[..., 0]


class Selection(NamedTuple):
    coords: jax.Array
    """(3,) the chosen pose (unconstrained mount coordinates)."""
    value: jax.Array
    """The chosen pose's score: Q on the hard image, averaged over the pose's neighbourhood
    (``config.smooth_samples``; without it Q at the pose)."""
    default_value: jax.Array
    """The mount's default pose's score, the same way."""
    starts: jax.Array
    """(R, 3) where the ascents started (the first: the default pose)."""
    ends: jax.Array
    """(R, 3) where they ended."""
    trace: jax.Array
    """(R, steps) the soft objective along each ascent."""
    checked: jax.Array
    """(K, R, 3) the iterates of each ascent scored on the hard image: every ``check_every``-th
    from the start (``checked[0] == starts``), and the end (``checked[-1] == ends``)."""
    checked_values: jax.Array
    """(K, R) Q at them (hard image); ``checked_values[0, 0]`` is Q at the default pose."""
    chosen: jax.Array
    """The chosen iterate's flat index into ``checked`` (``checked.reshape(-1, 3)[chosen] ==
    coords``): its Q at the pose itself is ``checked_values.reshape(-1)[chosen]``."""


def neighbourhood_offsets(config, key) -> jax.Array:
    """(M + 1, 3) the offsets (mount coordinates) a pose's score averages Q over: zero (the pose
    itself) and ``config.smooth_samples`` Gaussian ones of sd ``config.smooth_sd``."""
    M = int(config.smooth_samples)
    return jnp.concatenate([jnp.zeros((1, 3)),
                            float(config.smooth_sd) * jax.random.normal(key, (M, 3))])


def score_around(value_fn: Callable, coords: jax.Array, offsets: jax.Array) -> jax.Array:
    """The score of each pose ``coords`` (N, 3): ``value_fn`` (one pose -> Q) averaged over the
    pose moved by every one of ``offsets`` (kept within ``EDGE``; a non-finite Q counts as
    -inf), (N,). The same offsets for every pose, so poses are compared on the same draws."""
    around = jnp.clip(coords[:, None, :] + offsets[None], -EDGE, EDGE)
    near = jax.vmap(value_fn)(around.reshape(-1, 3))
    near = jnp.where(jnp.isfinite(near), near, -jnp.inf)
    return near.reshape(coords.shape[0], offsets.shape[0]).mean(axis=1)


def checked_steps(steps: int, every: int) -> np.ndarray:
    """The ascent iterates ``select_camera`` scores on the hard image: 0 (the start), every
    ``every``-th, and ``steps`` (the end)."""
    return np.unique(np.r_[np.arange(0, int(steps) + 1, max(1, int(every))), int(steps)])


def select_camera(env, q: Network, q_params, actor: Network, actor_params, state, key,
                  config) -> Selection:
    """The mount pose maximising ``Q(o(c), pi(o(c)))`` for ``state`` (module docstring): Adam
    ascent through the soft renderer from ``restarts`` starts, the winner by the hard image's Q
    among the iterates ``checked_steps(ascent_steps, check_every)`` of every ascent.
    ``config``: a ``SensingConfig`` (its ``restarts``, ``ascent_steps``, ``ascent_lr``, ``tau``,
    ``check_every``). Pure and jit-able (jit it with ``state`` and ``key`` as arguments)."""
    n = image_size(env, actor)
    keys = observed_keys(actor, q)
    soft, hard = observer(env, n, float(config.tau), keys), observer(env, n, keys=keys)

    def objective(obs_fn, c):
        o = obs_fn(state, c)
        return q_value(q, q_params, o, actor.apply(actor_params, o))

    default = jnp.asarray(env.mount.default, jnp.float32)
    starts = jnp.concatenate([default[None], uniform_coords(
        env.mount, key, (int(config.restarts) - 1,))], axis=0)
    tx = optax.adam(float(config.ascent_lr))

    def body(carry, _):
        # every restart at once: Adam is elementwise, so one optimiser over (R, 3) poses is R
        # independent ascents (and one scan of a vmapped gradient traces far faster than a
        # vmap of R scans: ``twinrl.learn.common.vmap_scan``)
        c, s = carry
        v, g = jax.vmap(jax.value_and_grad(lambda c: objective(soft, c)))(c)
        g = jnp.where(jnp.isfinite(g), g, 0.0)
        u, s = tx.update(-g, s, c)
        # within the box Q was trained on (``uniform_coords``): past it the sigmoid is flat,
        # the pose hardly moves, and Q would only be extrapolating
        c = jnp.clip(optax.apply_updates(c, u), -EDGE, EDGE)
        return (c, s), (v, c)

    steps = int(config.ascent_steps)
    _, (trace, path) = jax.lax.scan(body, (starts, tx.init(starts)), None, length=steps)
    # the soft image is only a surrogate: an ascent can pass the hard image's best on its way,
    # so the hard Q scores iterates along the way, not only where each ascent ends
    path = jnp.concatenate([starts[None], path], axis=0)[checked_steps(
        steps, int(config.check_every))]
    K, R = path.shape[:2]
    values = jax.vmap(lambda c: objective(hard, c))(path.reshape(K * R, 3))
    values = jnp.where(jnp.isfinite(values), values, -jnp.inf)
    flat = path.reshape(K * R, 3)
    if int(config.smooth_samples) == 0:
        best = jnp.argmax(values)
        return Selection(flat[best], values[best], values[0], starts, path[-1], trace.T, path,
                         values.reshape(K, R), best)
    # the best of K * R noisy estimates is picked partly for Q's error there (the winner's
    # curse), and a pose whose outcome a millimetre of hand-eye error changes is a poor choice:
    # the leading candidates, and the default, are scored by Q over a neighbourhood of poses
    T = min(int(config.smooth_top), K * R)
    cand = jnp.concatenate([jnp.zeros(1, jnp.int32), jnp.argsort(-values)[:T].astype(jnp.int32)])
    score = score_around(lambda c: objective(hard, c), flat[cand],
                         neighbourhood_offsets(config, jax.random.fold_in(key, 1)))
    pick = jnp.argmax(score)
    return Selection(flat[cand[pick]], score[pick], score[0], starts, path[-1], trace.T, path,
                     values.reshape(K, R), cand[pick])


def workspace_grid(mount, distance_coord, grid: tuple[int, int] = (15, 9)
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An azimuth x elevation grid over the mount's workspace (its edges left out) at one
    distance coordinate: ``(azimuths (A,), elevations (E,), coords (E * A, 3))``, the poses'
    unconstrained mount coordinates elevation-major (``coords.reshape(E, A, 3)``)."""
    az = np.linspace(*mount.azimuth, grid[0] + 2)[1:-1]
    el = np.linspace(*mount.elevation, grid[1] + 2)[1:-1]
    dist = float(np.asarray(mount.spherical(jnp.full(3, distance_coord, jnp.float32)))[2])
    coords = np.array([mount.coords_of([a, e, dist]) for e in el for a in az], np.float32)
    return az, el, coords


def landscape(env, q: Network, q_params, actor: Network, actor_params, state, distance_coord,
              grid: tuple[int, int] = (15, 9)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Q (hard images) over an azimuth x elevation grid of the workspace at one distance
    coordinate: ``(azimuths (A,), elevations (E,), values (E, A))`` in radians."""
    az, el, coords = workspace_grid(env.mount, distance_coord, grid)
    hard = observer(env, image_size(env, actor), keys=observed_keys(actor, q))

    @jax.jit
    def values(cs):
        def one(c):
            o = hard(state, c)
            return q_value(q, q_params, o, actor.apply(actor_params, o))
        return jax.lax.map(one, cs)

    return az, el, np.asarray(values(jnp.asarray(coords))).reshape(len(el), len(az))


def view_outcomes(env, actor: Network, actor_params, keys: jax.Array, coords: jax.Array):
    """The image actor's episodes in the simulator from ``reset(keys[i])`` with the mount held
    at ``coords[i]`` (N, 3) -- a deployment's counterpart in the (identified) twin, where the
    camera choice of ``select_camera`` can be compared with the default and random poses
    without a real episode (``bench/sensing.py --where sim``): ``(returns (N,), successes (N,))``.
    Pure and jit-able."""
    observe = observer(env, image_size(env, actor), keys=tuple(actor.obs_spec))
    ep = held_episodes(env, observe, lambda o: actor.apply(actor_params, o), keys, coords=coords)
    return ep.rewards.sum(1), ep.success


def q_predictions(q, q_params, data) -> np.ndarray:
    """Q at every example of a ``twinrl.learn.sensing.SensingData``, shaped as its targets
    (S, C, K)."""
    flat = lambda x: x.reshape((-1,) + x.shape[3:])  # noqa: E731
    obs = jax.tree_util.tree_map(flat, data.obs)
    return np.asarray(jax.jit(lambda p, o, a: q_value(q, p, o, a))(
        q_params, obs, flat(data.actions))).reshape(data.targets.shape)


class CameraCheck(NamedTuple):
    """Q's choice against the default camera on the same fresh starts in the (identified) twin
    (``check_choice``): per start, the success and return with each camera, and Q's poses."""

    selected: np.ndarray
    default: np.ndarray
    selected_return: np.ndarray
    default_return: np.ndarray
    coords: np.ndarray

    @property
    def pays(self) -> bool:
        """Q's choice succeeded on more of the starts than the default camera (a tie keeps the
        default: moving the camera costs steps, and no start says it helps)."""
        return int(self.selected.sum()) > int(self.default.sum())

    def as_dict(self) -> dict:
        return {"episodes": int(len(self.selected)),
                "selected_success": float(self.selected.mean()),
                "default_success": float(self.default.mean()),
                "selected_successes": self.selected.astype(bool).tolist(),
                "default_successes": self.default.astype(bool).tolist(),
                "selected_return": float(self.selected_return.mean()),
                "default_return": float(self.default_return.mean()),
                "coords": self.coords.tolist(), "pays": self.pays}


def check_choice(env, q: Network, q_params, actor: Network, actor_params, config, keys,
                 on_choice: Callable[[int], None] | None = None) -> CameraCheck:
    """The image actor's episodes in ``env`` (the identified twin) from ``reset(keys[i])``, once
    with the pose ``select_camera`` chooses from that start (``config``: the Q's
    ``SensingConfig``) and once with the mount's default pose -- what the deployment would gain
    by moving the camera, measured without a real episode. ``on_choice(i)`` is called after
    each choice (progress)."""
    choose = jax.jit(lambda k: select_camera(env, q, q_params, actor, actor_params, env.reset(k),
                                             jax.random.fold_in(k, 1), config).coords)
    coords = []
    for i, k in enumerate(keys):
        coords.append(choose(k).block_until_ready())  # a progress line means a choice made
        if on_choice is not None:
            on_choice(i)
    coords = jnp.stack(coords)
    run = jax.jit(lambda k, c: view_outcomes(env, actor, actor_params, k, c))
    default = jnp.tile(jnp.asarray(env.mount.default, jnp.float32), (len(keys), 1))
    r_sel, ok_sel = (np.asarray(x, np.float64) for x in run(keys, coords))
    r_def, ok_def = (np.asarray(x, np.float64) for x in run(keys, default))
    return CameraCheck(ok_sel, ok_def, r_sel, r_def, np.asarray(coords, np.float64))
