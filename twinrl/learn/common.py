"""What every trainer shares: the ``train`` contract, policy evaluation and metric bookkeeping.

The trainer contract (Brax's, made resumable)::

    policy, params, metrics = train(env, config, rng, *, progress_fn=None, checkpoint_fn=None,
                                    restore=None)

- ``env``: a ``twinrl.envs.Env``; ``config``: the algorithm's frozen dataclass; ``rng``: a key.
- ``policy``: a ``twinrl.learn.networks.Network``; ``policy.apply(params, obs)`` is the
  deterministic action in [-1, 1].
- ``metrics``: ``dict[str, list[float]]``, one entry per epoch, always including ``epoch``,
  ``env_steps`` (cumulative simulated steps, line searches and gradient re-simulations included),
  ``wall_s`` (cumulative seconds, compile included), ``return`` (mean undiscounted evaluation
  return of the deterministic policy over ``eval_episodes`` full episodes) and ``grad_norm``.
- ``progress_fn(epoch, metrics_of_this_epoch)`` is called after every epoch.
- ``checkpoint_fn(epoch, train_state, metrics)`` is called after every epoch with the trainer's
  whole state (a pytree of arrays of fixed structure: params, optimiser state, rng, counters) and
  the metric history so far, which the caller may save (``twinrl.learn.checkpoint``).
- ``restore(template_state) -> (train_state, metrics)``: the trainer builds its initial state, hands
  it to ``restore`` as the structure to fill, and continues from epoch ``len(metrics['epoch'])``.
  The result equals an uninterrupted run's with the same seed (wall clock aside), because every
  random draw comes from the key carried in the state.

Also here, because PODS, HDS and their critic all use it: the policy regression onto targets
(``make_regress``: full-batch steps of ``make_optimizer``'s NaN guard, clip and Adam on the
weighted squared error ``regression_loss``; PODS Sec. 4, "policy update").
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, Collection, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import NamedSharding, PartitionSpec

from twinrl.learn import distributed
from twinrl.physics.gradients import global_norm, hygiene

__all__ = ["raw_key", "evaluate", "make_evaluator", "MetricLog", "ProgressFn", "CheckpointFn",
           "RestoreFn", "compile_key", "JSONConfig", "tree_where", "make_optimizer",
           "regression_loss", "make_regress", "make_minibatch_fit", "rgb_jitter", "vmap_scan",
           "Episodes", "held_episodes"]

ProgressFn = Callable[[int, dict[str, float]], None]
CheckpointFn = Callable[[int, Any, dict[str, list[float]]], None]
RestoreFn = Callable[[Any], tuple[Any, dict[str, list[float]]]]


def compile_key(config) -> Any:
    """The part of a trainer's frozen config its compiled functions depend on (a cache key):
    ``epochs`` changes no compiled function, so a longer or resumed run reuses them."""
    return dataclasses.replace(config, epochs=1)


def _interval(text: str) -> tuple[float, float, bool, bool]:
    """``"(0, 1]"`` -> ``(0.0, 1.0, False, True)``: bounds and whether each is closed."""
    if text[0] not in "([" or text[-1] not in ")]":
        raise ValueError(f"not an interval: {text!r}")
    lo, hi = (float(x) for x in text[1:-1].split(","))
    return lo, hi, text[0] == "[", text[-1] == "]"


class JSONConfig:
    """Mixin of a frozen config dataclass saved in checkpoints as JSON: ``to_dict`` (tuples as
    lists) and ``from_dict`` (the dataclass's ``__post_init__`` turns the lists back).

    ``check_fields`` validates fields declaratively from ``__post_init__``, with one uniform
    one-line message per failure: ``SHACConfig.horizon must be an integer >= 1, got 0``.
    """

    def check_fields(self, *, at_least_one: tuple[str, ...] = (), positive: tuple[str, ...] = (),
                     non_negative: tuple[str, ...] = (), within: dict[str, str] | None = None,
                     choices: dict[str, Collection] | None = None, widths: tuple[str, ...] = (),
                     optional: tuple[str, ...] = ()) -> None:
        """Raise ``ValueError`` naming the first field that breaks its rule.

        ``at_least_one``: integers >= 1; ``positive``: > 0; ``non_negative``: >= 0; ``within``:
        field -> interval such as ``"[0, 1]"`` or ``"(0, 1]"``; ``choices``: field -> allowed
        values; ``widths``: sequences of layer widths, each an integer >= 1 (stored back as a
        tuple of ints, so JSON lists round-trip). A field named in ``optional`` may also be None.
        """
        cls = type(self).__name__

        def fail(name, rule):
            none = " or None" if name in optional else ""
            raise ValueError(f"{cls}.{name} must be {rule}{none}, got {getattr(self, name)!r}")

        def number(v):
            return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)

        def is_int(v):
            return number(v) and float(v).is_integer()

        def checked(names):  # (name, value) of each field to check: optional Nones pass
            return [(n, getattr(self, n)) for n in names
                    if not (n in optional and getattr(self, n) is None)]

        for name, v in checked(widths):
            if not isinstance(v, (tuple, list)) or not all(is_int(x) and x >= 1 for x in v):
                fail(name, "layer widths that are integers >= 1")
            object.__setattr__(self, name, tuple(int(x) for x in v))
        rules = [(at_least_one, "an integer >= 1", lambda v: is_int(v) and v >= 1),
                 (positive, "> 0", lambda v: number(v) and v > 0),
                 (non_negative, ">= 0", lambda v: number(v) and v >= 0)]
        for names, rule, ok in rules:
            for name, v in checked(names):
                if not ok(v):
                    fail(name, rule)
        for name, v in checked(within or {}):
            lo, hi, lo_in, hi_in = _interval(within[name])
            inside = number(v) and (lo <= v if lo_in else lo < v) and (v <= hi if hi_in else v < hi)
            if not inside:
                fail(name, f"in {within[name]}")
        for name, v in checked(choices or {}):
            if v not in choices[name]:
                fail(name, f"one of {', '.join(repr(a) for a in choices[name])}")

    def to_dict(self) -> dict[str, Any]:
        return {k: list(v) if isinstance(v, tuple) else v
                for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]):
        return cls(**d)


def tree_where(mask: jax.Array, a, b):
    """Per batch entry (leading axis of ``mask``): ``a`` where ``mask`` else ``b``, leaf by leaf
    (e.g. a fresh episode's state for the environments whose episode ended)."""
    return jax.tree_util.tree_map(
        lambda x, y: jnp.where(mask.reshape(mask.shape + (1,) * (x.ndim - 1)), x, y), a, b)


def vmap_scan(body: Callable, init, consts=None, xs=None, length: int | None = None):
    """What ``jax.vmap`` over the leading axis of ``init``, ``consts`` and ``xs`` of
    ``lax.scan(lambda c, x: body(c, x, consts), init, xs, length)`` gives -- ``(final (B, ...),
    ys (B, T, ...))``, ``xs`` (B, T, ...) -- built as one scan of the vmapped body.

    Same values, traced several times faster for a big body (an arm episode: renderer, actor,
    physics). JAX batches a vmapped scan by batching its body's jaxpr again for every carry that
    turns batched in a step (a fixpoint: a state from ``reset`` has such leaves, Adam's zero
    moments too), and a vmap of that vmap batches the batched body once more; here the body is
    batched once, while it is traced. Sensing's episodes of 6 start states x 3 poses of peg
    insertion: trace 36.6 s -> 9.5 s (2 cores). Anything not batched: close ``body`` over it.
    """
    step = jax.vmap(body)
    swap = lambda tree: jax.tree_util.tree_map(lambda x: jnp.swapaxes(x, 0, 1), tree)  # noqa
    final, ys = jax.lax.scan(lambda c, x: step(c, x, consts), init,
                             None if xs is None else swap(xs), length=length)
    return final, swap(ys)


class Episodes(NamedTuple):
    """A batch of B episodes of T steps (``held_episodes``)."""

    obs: Any
    """(B, T, ...) the observations before each step."""
    states: Any
    """(B, T) the ``State`` before each step."""
    actions: jax.Array
    """(B, T, m) the actions sent."""
    rewards: jax.Array
    """(B, T) each step's reward."""
    success: jax.Array
    """(B,) the final state's ``env.success`` (zeros for a task without one)."""


def held_episodes(env, observe: Callable, act: Callable | None, keys: jax.Array,
                  actions: jax.Array | None = None, coords: jax.Array | None = None,
                  noise: jax.Array | None = None) -> Episodes:
    """Episodes from ``env.reset(keys[i])``, observed by ``observe(state, coords[i])`` -- an image
    actor's camera held at ``coords[i]`` (B, 3) the whole episode, or ``None`` -- and acted by
    ``actions`` (B, T, m) if given, else by ``act(observation)`` plus ``noise`` (B, T, m) if
    given, clipped to [-1, 1] (DAgger's noisy visits): the image actor's episodes of imitation
    (demonstrations re-rendered, evaluation, DAgger's visits), of the sensing Q's data and of a
    camera choice's outcomes (``twinrl.learn.camera_choice.view_outcomes``). One scan of the
    vmapped step (``vmap_scan``). Pure and jit-able; what the caller does not use of it, XLA
    drops. ``Episodes.actions`` are the actions sent (noise included)."""
    if actions is not None and noise is not None:
        raise ValueError("held_episodes takes actions or noise, not both")

    def body(s, x, c):
        obs = observe(s, c)
        if actions is not None:
            a = x
        else:
            a = act(obs)
            if noise is not None:
                a = jnp.clip(a + x, -1.0, 1.0)
        s2 = env.step(s, a)
        return s2, (obs, s, a, s2.reward)

    final, (obs, states, sent, rewards) = vmap_scan(
        body, jax.vmap(env.reset)(keys), coords, actions if actions is not None else noise,
        length=env.episode_length)
    q, v = final.pipeline_state.qpos, final.pipeline_state.qvel
    success = (jax.vmap(env.success)(q, v).astype(jnp.float32) if hasattr(env, "success")
               else jnp.zeros(rewards.shape[:1], jnp.float32))
    return Episodes(obs, states, sent, rewards, success)


def raw_key(rng) -> jax.Array:
    """A uint32[2] key from an int seed (None: 0), a raw key or a typed key; trainers carry raw
    keys in their state so that checkpoints hold plain arrays."""
    if rng is None:
        rng = 0
    if isinstance(rng, (int, np.integer)):
        return jax.random.PRNGKey(int(rng))
    if isinstance(rng, jax.Array) and jnp.issubdtype(rng.dtype, jax.dtypes.prng_key):
        rng = jax.random.key_data(rng)
    rng = jnp.asarray(rng)
    if rng.shape != (2,) or rng.dtype != jnp.uint32:
        raise ValueError(f"rng must be an int seed, a jax.random.PRNGKey (uint32[2]) or a typed "
                         f"key, got {rng.dtype}{list(rng.shape)}")
    return rng


def make_evaluator(env, apply_fn: Callable, episodes: int, episode_length: int | None = None):
    """A jitted ``evaluate(params, rng) -> returns (episodes,)`` of the deterministic policy.

    Every episode runs the full ``episode_length`` (an episode that diverged stops earning: reward
    after ``done`` is masked).
    """
    T = int(episode_length or env.episode_length)

    @jax.jit
    def evaluate(params, rng):
        def body(s, _, __):
            a = apply_fn(params, s.obs)
            s2 = env.step(s, a)
            return s2, jnp.where(s.done > 0, 0.0, s2.reward)

        states = jax.vmap(env.reset)(jax.random.split(rng, episodes))
        return vmap_scan(body, states, length=T)[1].sum(-1)

    return evaluate


def evaluate(env, apply_fn, params, rng, episodes: int = 8) -> np.ndarray:
    """Returns of ``episodes`` deterministic episodes in ``env`` (compiles each call: prefer
    ``make_evaluator`` inside a trainer)."""
    return np.asarray(make_evaluator(env, apply_fn, episodes)(params, rng))


class MetricLog:
    """Per-epoch metric history with cumulative wall clock; ``as_dict()`` is ``train``'s metrics.

    ``history`` restores a log from a train state (``to_arrays``) so that a resumed run's metrics
    continue the killed run's; wall-clock time continues from the recorded total.
    """

    def __init__(self, history: dict[str, Any] | None = None):
        self.history: dict[str, list[float]] = {
            k: [float(x) for x in np.asarray(v).ravel()] for k, v in (history or {}).items()}
        self._t0 = time.perf_counter() - (self.history["wall_s"][-1] if self.history.get("wall_s")
                                          else 0.0)

    def record(self, **values: Any) -> dict[str, float]:
        row = {k: float(np.asarray(v)) for k, v in values.items()}
        row["wall_s"] = time.perf_counter() - self._t0
        for k, v in row.items():
            self.history.setdefault(k, []).append(v)
        return row

    def as_dict(self) -> dict[str, list[float]]:
        return {k: list(v) for k, v in self.history.items()}

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {k: np.asarray(v, np.float64) for k, v in self.history.items()}


# --------------------------------------------------------------------------- regression
def regression_loss(apply_fn, params, obs, targets, weights):
    """Weighted mean squared error ``sum w |pi(o) - a*|^2 / sum w`` (PODS Sec. 4 policy update)."""
    pred = apply_fn(params, obs)
    se = jnp.sum(jnp.square(pred - targets), axis=-1)
    return jnp.sum(weights * se) / jnp.maximum(jnp.sum(weights), 1.0)


def make_minibatch_fit(apply_fn, tx, steps: int, batch: int,
                       augment: Callable[[Any, jax.Array], Any] | None = None,
                       loop: str = "auto", mesh="auto"):
    """``fit(params, opt_state, obs, targets, n, key, weights=None) -> (params, opt_state,
    losses)``: ``steps`` steps of ``tx`` on ``regression_loss`` over minibatches of ``batch``
    rows drawn from the first ``n`` rows of ``obs`` (any pytree, e.g. a dict observation) and
    ``targets``, weighted by ``weights`` (rows,) if given; ``augment(obs, key)`` transforms each
    minibatch (``rgb_jitter``). ``losses``: (steps,). The imitation actor's and the sensing Q's
    fit.

    ``loop``: ``"scan"`` runs the steps in one compiled ``lax.scan``; ``"python"`` calls one
    compiled step ``steps`` times; ``"auto"`` takes ``"python"`` where ``obs`` holds images
    (a leaf of rank >= 4: rows, height, width, channels) and ``"scan"`` otherwise. XLA's CPU
    backend runs a convolution's gradient inside a loop body far slower than at the top level
    (jax-ml/jax#12868): the image actor's step (64x64x5, batch 256, the keypoint CNN, 2 cores)
    takes 9.3 s inside the scan and 0.25 s called alone (``bench/learn_fit.py`` (in git history)); a vector
    fit's, 1.4 and 1.7 ms. Both draw the same minibatches (step i uses ``split(key, steps)[i]``).
    ``fit.loop_for(obs)`` says which loop a fit on ``obs`` runs.

    ``mesh`` (a ``("batch",)`` mesh over every process's devices, ``twinrl.learn.distributed``):
    data-parallel. The data and the parameters are replicated, every process draws the same
    minibatch indices from the same key, and each minibatch's rows are split over the mesh, so
    each device takes the gradient of its rows and XLA all-reduces the mean: the same fit as on
    one device up to the order of that sum. ``batch`` must be a multiple of the device count;
    the returned parameters and optimiser state are host (NumPy) copies. None: one device;
    ``"auto"``: the global mesh when several processes run (``jax.distributed``: the imitation
    actor's and the sensing Q's fits), else one device."""
    if loop not in ("auto", "scan", "python"):
        raise ValueError(f"loop must be 'auto', 'scan' or 'python', got {loop!r}")
    if isinstance(mesh, str):
        mesh = distributed.global_mesh() if distributed.is_distributed() else None
    if mesh is not None and batch % mesh.devices.size:
        raise ValueError(f"batch ({batch}) must be a multiple of the device count "
                         f"({mesh.devices.size}) to split each minibatch over the mesh")
    ones = jnp.ones((batch,))

    def rows(tree):  # a minibatch's rows split over the mesh (nothing on one device)
        if mesh is None:
            return tree
        return jax.tree_util.tree_map(lambda x: jax.lax.with_sharding_constraint(
            x, NamedSharding(mesh, PartitionSpec("batch", *([None] * (x.ndim - 1))))), tree)

    def one(p, s, obs, targets, n, k, weights):
        k_idx, k_aug = (k, None) if augment is None else jax.random.split(k)
        idx = jax.random.randint(k_idx, (batch,), 0, n)
        o = rows(jax.tree_util.tree_map(lambda x: x[idx], obs))
        if augment is not None:
            o = augment(o, k_aug)
        w = rows(ones if weights is None else weights[idx])
        value, g = jax.value_and_grad(regression_loss, argnums=1)(apply_fn, p, o,
                                                                  rows(targets[idx]), w)
        u, s = tx.update(g, s, p)
        return optax.apply_updates(p, u), s, value

    @jax.jit
    def scanned(params, opt, obs, targets, n, key, weights=None):
        def body(carry, k):
            p, s, value = one(*carry, obs, targets, n, k, weights)
            return (p, s), value

        (params, opt), losses = jax.lax.scan(body, (params, opt), jax.random.split(key, steps))
        return params, opt, losses

    step = jax.jit(one)

    def stepwise(params, opt, obs, targets, n, key, weights=None):
        losses = []
        for k in jax.random.split(key, steps):
            params, opt, value = step(params, opt, obs, targets, n, k, weights)
            losses.append(value)
        return params, opt, jnp.stack(losses) if losses else jnp.zeros((0,))

    def loop_for(obs) -> str:
        if loop != "auto":
            return loop
        return "python" if any(jnp.ndim(x) >= 4 for x in jax.tree_util.tree_leaves(obs)) else "scan"

    def fit(params, opt, obs, targets, n, key, weights=None):
        run = stepwise if loop_for(obs) == "python" else scanned
        if mesh is None:
            return run(params, opt, obs, targets, n, key, weights)
        everywhere = NamedSharding(mesh, PartitionSpec())
        args = jax.device_put(distributed.to_host((params, opt, obs, targets, n, key, weights)),
                              everywhere)
        return distributed.to_host(run(*args))

    fit.loop_for = loop_for
    return fit


def rgb_jitter(amount: float) -> Callable[[Any, jax.Array], Any]:
    """``augment(obs, key)`` for ``make_minibatch_fit``: the RGB channels (the first three) of
    every ``pixels/*`` image get a per-image, per-channel gain in ``1 +- amount`` and an offset in
    ``+- amount / 2``, clipped to [0, 1] -- the simulator's shading is not the real camera's
    (peg: 0.06 mean absolute RGB difference between our renderer and MuJoCo's OpenGL at the
    same pose), and an actor that leans on exact colours would not transfer."""

    def augment(obs, key):
        out = dict(obs)
        for i, k in enumerate(sorted(k for k in obs if k.startswith("pixels/"))):
            x = obs[k]
            kg, kb = jax.random.split(jax.random.fold_in(key, i))
            shape = x.shape[:-3] + (1, 1, 3)
            gain = 1.0 + jax.random.uniform(kg, shape, minval=-amount, maxval=amount)
            bias = jax.random.uniform(kb, shape, minval=-amount / 2, maxval=amount / 2)
            rgb = jnp.clip(x[..., :3] * gain + bias, 0.0, 1.0)
            out[k] = jnp.concatenate([rgb, x[..., 3:]], axis=-1)
        return out

    return augment


def make_optimizer(learning_rate: float, max_grad_norm: float | None):
    """NaN guard, global-norm clip, Adam: a non-finite update never reaches the parameters."""
    return optax.chain(hygiene(max_grad_norm), optax.adam(learning_rate))


def make_regress(apply_fn, optimizer, steps: int):
    """A jitted ``regress(params, opt_state, obs, targets, weights)`` of ``steps`` full-batch
    steps. Returns ``(params, opt_state, final_loss, first_grad_norm, initial_loss)`` (the loss
    before the first step says how far the targets moved; the final one how well the policy fits
    them); with no weight at all
    (nothing accepted) the params and optimiser state are returned unchanged (Adam's momentum
    would otherwise keep moving them)."""

    def regress(params, opt_state, obs, targets, weights):
        w = weights.reshape(-1).astype(jnp.float32)
        obs = obs.reshape(w.shape[0], -1)
        targets = targets.reshape(w.shape[0], -1)
        # where(), so a masked NaN cannot leak through 0 * NaN
        keep = w > 0
        obs = jnp.where(keep[:, None], obs, 0.0)
        targets = jnp.where(keep[:, None], targets, 0.0)

        def body(carry, _):
            p, s = carry
            loss, g = jax.value_and_grad(
                lambda q: regression_loss(apply_fn, q, obs, targets, w))(p)
            u, s = optimizer.update(g, s, p)
            return (optax.apply_updates(p, u), s), (loss, global_norm(g))

        (p, s), (losses, norms) = jax.lax.scan(body, (params, opt_state), None, length=steps)
        any_w = jnp.sum(w) > 0
        pick = lambda new, old: jax.tree_util.tree_map(  # noqa: E731
            lambda a, b: jnp.where(any_w, a, b), new, old)
        final = regression_loss(apply_fn, p, obs, targets, w)
        return (pick(p, params), pick(s, opt_state), jnp.where(any_w, final, 0.0), norms[0],
                jnp.where(any_w, losses[0], 0.0))

    return jax.jit(regress)
