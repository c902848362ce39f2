"""The sensing-aware Q-function and the camera choice by gradient through the renderer (SAM-RL).

SAM-RL (Lv et al., RSS 2023, Sec. 4.3) lets the robot choose where to look: a Q-function scores
what the image actor would do from the image a camera pose gives, ``Q(o(P_c), pi(o(P_c)))``, and
the camera goes to the pose that maximises it -- found by gradient ascent *through the
differentiable renderer* w.r.t. the pose. Here:

- **Data** (``sensing_data``): from ``states`` fresh start states, the image actor (``twinrl.learn
  .imitation``, ``observation="pixels"``) runs whole episodes with the camera held at each of
  ``cameras`` poses drawn uniformly over the mount's workspace. Every ``every``-th step gives one
  example: the observation there, the actor's action there, and the target.
- **Target** (``SensingConfig.target``): ``"return"`` (default), the actor's mean reward per step
  from that step to the episode's end (return-to-go / steps left, in the reward's [0, 1] units),
  or ``"success"``, the episode's final success (0/1). The return is the default because it is
  dense: where the actor fails from every pose (most poses of a hard state) success is 0 from all
  of them and gives Q nothing to rank, while the reward's shaped terms (reach, alignment) still
  say from which poses the actor got closer. Both are Monte-Carlo values of the actor that will be
  deployed, not of an optimal policy: Q answers "how well does *this* actor do from this view".
- **Q** (``train``): a ``twinrl.learn.networks`` network of the actor's observation (joint
  angles and velocities, the 64 x 64 RGB-D + target-mask image; for an actor on the fitted
  pose, the pose and what its fit stood on too: ``q_inputs``) and the action, regressed onto
  the targets. Its figures (``metrics``) are on held-out start states: the loss, the rank
  correlation between Q and the target across the poses of one state (what a camera choice needs
  Q to get right; a state's own difficulty does not matter there), the target at the pose Q
  prefers among the sampled ones, against their mean and their best, and how often the camera
  choice below raises Q above the default pose.
- **Choice** (``select_camera``, in ``twinrl.learn.camera_choice`` with Q's landscape;
  ``twinrl sense`` is ``twinrl.sense``): Adam ascent of ``J(c) = Q(o(c), pi(o(c)))`` in the mount's
  unconstrained coordinates (``CameraMount``: a sigmoid keeps every pose in its workspace), the
  image rendered soft (``tau``) so that the pose has a gradient through silhouettes, from the
  default pose and ``restarts - 1`` random ones; the winner is chosen by ``J`` on the *hard*
  image (the one the actor will see) among every ``check_every``-th iterate of every ascent
  (its start and end included), so the choice is never worse, by Q, than the default pose.

``twinrl train --algo sensing --env TASK --set actor=DIR`` trains Q for the image actor saved in
``DIR`` (a ``twinrl train --algo imitation --set observation=pixels`` run); ``twinrl sense --env
TASK --checkpoint DIR`` chooses a pose for a start state and plots Q over the workspace.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.learn.camera_choice import (Selection, image_size, observer, q_predictions,
                                        q_value, select_camera, uniform_coords)
from twinrl.learn.augment import image_augment
from twinrl.learn.common import (JSONConfig, MetricLog, held_episodes, make_minibatch_fit,
                                 make_optimizer, raw_key)
from twinrl.learn.networks import Network, NetworkConfig, make_network
from twinrl.learn.ranking import evaluate_ranking, rank_corr_per_state

__all__ = ["SensingConfig", "SensingError", "SensingData", "Selection", "uniform_coords",
           "observer", "sensing_data", "q_inputs", "make_q", "fit_q", "q_value", "train",
           "select_camera", "evaluate_ranking", "q_predictions", "rank_corr_per_state",
           "load_actor"]


@dataclasses.dataclass(frozen=True)
class SensingConfig(JSONConfig):
    actor: str = ""
    """The image actor's policy checkpoint (a ``twinrl train --algo imitation --set
    observation=pixels`` run directory or its ``policy/``); ``train``'s ``actor`` argument takes
    precedence."""
    target: str = "return"
    """``"return"`` (mean reward per step to the episode's end) or ``"success"`` (module
    docstring says why the return is the default)."""
    states: int = 32
    """Start states of the training data (a fifth more are drawn and held out). Q's rank per
    state on 40 fresh states x 8 poses of a loop's identified twin (mean of 3 fit seeds), 32
    states -> 64: needle 0.46 -> 0.49, spatula 0.53 -> 0.57 (``bench/q_rank.py --retrain
    states=64`` on spatula twin 0's loop: 0.54 -> 0.61, Q's training 37 -> 82 s); the data's cost
    doubles with it (the needle's episodes fit the target's pose at every step: minutes)."""
    cameras: int = 8
    """Camera poses per start state, uniform over the mount's workspace."""
    every: int = 10
    """One example every this many steps of each episode."""
    rgb_jitter: float = 0.1
    """RGB gain/offset jitter of each training image (``common.rgb_jitter``; 0: none)."""
    random_shift: int = 0
    """Each training image shifted by up to this many pixels, edges repeated (DrQ,
    ``augment.random_shift``; 0: none). Images only: an actor on the fitted pose or the target
    cloud gives Q no image."""
    hidden: tuple[int, ...] = (256, 256)
    ensemble: int = 1
    """Q's members (``NetworkConfig.ensemble``): each fitted to the targets on its own, Q their
    mean. Five members, measured as ``states``: needle 0.46 -> 0.49, spatula 0.53 -> 0.51 (64
    states: 0.49 -> 0.51, 0.57 -> 0.55), within a fit seed's spread (0.03-0.04): one."""
    learning_rate: float = 1e-3
    max_grad_norm: float | None = 1.0
    fit_steps: int = 2000
    batch_size: int = 128
    restarts: int = 6
    """Ascents per camera choice: from the default pose and ``restarts - 1`` random ones."""
    ascent_steps: int = 20
    ascent_lr: float = 0.3
    """Adam's step in the mount's unconstrained coordinates."""
    tau: float = 1.0
    """Soft-silhouette width (pixels) of the renders the ascent differentiates."""
    check_every: int = 3
    """Every this many ascent steps (and at its start and end) the pose is scored on the hard
    image; the choice is the best scored pose (``camera_choice.checked_steps``)."""
    smooth_samples: int = 8
    """Score the ``smooth_top`` best scored poses (and the default) by Q averaged over the pose
    and this many poses around it (``camera_choice.select_camera``); 0: by Q at the pose alone."""
    smooth_top: int = 8
    smooth_sd: float = 0.1
    """The spread (sd, mount coordinates) of the poses around each candidate."""

    def __post_init__(self):
        self.check_fields(at_least_one=("states", "every", "fit_steps", "batch_size", "restarts",
                                        "ascent_steps", "check_every", "smooth_top",
                                        "ensemble"),
                          non_negative=("rgb_jitter", "smooth_samples", "random_shift"),
                          positive=("ascent_lr", "tau", "smooth_sd"), widths=("hidden",),
                          choices={"target": ("return", "success")})
        if int(self.cameras) < 2:
            raise ValueError(f"cameras must be >= 2 (Q must compare poses), got {self.cameras}")


class SensingError(ValueError):
    """A missing or unsuitable actor or Q checkpoint, or a task without a camera mount (the CLI
    prints it as one line)."""


def load_actor(path) -> tuple[Network, object, dict]:
    """The image actor ``(network, params, meta)`` from a policy checkpoint; a one-line error if
    it is not an image actor of an arm task."""
    from twinrl.learn.checkpoint import KINDS, load_policy, read_meta

    where, meta = read_meta(path)
    if meta["kind"] != "image_actor":
        raise SensingError(f"{where} is {KINDS[meta['kind']]}, not an image actor; train one "
                           f"with --algo imitation --set observation=pixels (or pose)")
    net, params, meta = load_policy(path)
    return net, params, meta


class SensingData(NamedTuple):
    obs: dict
    """Observations (S, C, K, ...): start state, camera pose, example along the episode."""
    actions: jax.Array
    """(S, C, K, m) the actor's actions there."""
    targets: jax.Array
    """(S, C, K) return-to-go per step left, or the episode's success."""
    coords: jax.Array
    """(S, C, 3) the camera poses (unconstrained mount coordinates)."""
    returns: jax.Array
    """(S, C) the episodes' returns."""
    success: jax.Array
    """(S, C) the episodes' final success."""


def sensing_data(env, actor: Network, actor_params, config: SensingConfig, keys: jax.Array,
                 coords: jax.Array) -> SensingData:
    """The actor's episodes from ``reset(keys[i])`` with the camera held at ``coords[i, j]``
    (S, C, 3), and the examples Q learns from (module docstring)."""
    observe = observer(env, image_size(env, actor), keys=tuple(q_inputs(actor)))
    T = env.episode_length
    picks = jnp.arange(0, T, int(config.every))

    @jax.jit
    def run(keys, coords):
        S, C = coords.shape[:2]
        ep = held_episodes(env, observe, lambda o: actor.apply(actor_params, o),
                           jnp.repeat(keys, C, axis=0), coords=coords.reshape(S * C, -1))
        # episode i * C + j: start state i, camera pose j
        obs, acts, rewards, ok = ep.obs, ep.actions, ep.rewards, ep.success
        to_go = jnp.cumsum(rewards[:, ::-1], axis=1)[:, ::-1] / jnp.arange(T, 0, -1)
        target = (to_go[:, picks] if config.target == "return"
                  else jnp.broadcast_to(ok[:, None], (S * C, picks.size)))
        out = (jax.tree_util.tree_map(lambda x: x[:, picks], obs), acts[:, picks], target,
               rewards.sum(1), ok)
        return jax.tree_util.tree_map(lambda x: x.reshape((S, C) + x.shape[1:]), out)

    obs, acts, targets, returns, ok = run(keys, coords)
    return SensingData(obs, acts, targets, coords, returns, ok)


def q_inputs(actor: Network) -> dict:
    """Q's observation spec (the action aside): the actor's, and for an actor that acts on the
    target's fitted pose (``"estimate"``) also the commanded ``"camera"`` pose and the fit's
    ``"support"`` (``ArmTask.observation_from_image``: its pixel count and residual) -- the
    estimate alone is nearly the same from every pose it is right from, and Q has to tell
    from where it is not."""
    spec = dict(actor.obs_spec)
    if "estimate" in spec:
        spec.update(camera=(3,), support=(2,))
    return spec


def make_q(actor: Network, action_size: int, config: SensingConfig) -> Network:
    """Q's network: ``q_inputs(actor)`` plus the action, to one linear output."""
    spec = q_inputs(actor)
    spec["action"] = (int(action_size),)
    return make_network(spec, 1, NetworkConfig(hidden=tuple(config.hidden), activation="elu",
                                               output="linear", layer_norm=True,
                                               ensemble=int(config.ensemble)))


def fit_q(q: Network, params, data: SensingData, config: SensingConfig, key: jax.Array):
    """Regress Q onto ``data``'s targets (``config``'s fit fields; images augmented):
    ``(params, losses)``, the minibatches' squared error per step (an ensemble's: every
    member's on its own, summed over the members)."""
    flat = lambda x: x.reshape((-1,) + x.shape[3:])  # noqa: E731
    obs, targets = jax.tree_util.tree_map(flat, data.obs), flat(data.targets)[:, None]
    apply = q.apply
    if q.members is not None:  # each member regressed on the targets: (rows, members)
        apply = lambda p, o: q.members(p, o)[..., 0]  # noqa: E731
        targets = jnp.tile(targets, (1, int(q.config.ensemble)))
    tx = make_optimizer(config.learning_rate, config.max_grad_norm)
    fit = make_minibatch_fit(apply, tx, int(config.fit_steps), int(config.batch_size),
                             image_augment(config.rgb_jitter, config.random_shift))
    params, _, losses = fit(params, tx.init(params), {**obs, "action": flat(data.actions)},
                            targets, targets.shape[0], key)
    return params, losses


def train(env, config: SensingConfig = SensingConfig(), rng: jax.Array | int = 0, *,
          actor: tuple[Network, object] | None = None,
          progress_fn: Callable[[int, dict], None] | None = None, checkpoint_fn=None,
          restore=None):
    """Q for the image actor (``actor=(network, params)``, default ``config.actor``'s
    checkpoint) on ``env``: data, fit, held-out figures (module docstring). Not resumable.

    Returns ``(q, q_params, metrics)`` with one row: ``pairs`` (training examples), ``loss``,
    ``val_loss``, ``rank_corr``, ``rank_corr_pooled``, ``target_q_choice`` / ``target_mean_pose`` /
    ``target_best_pose``, ``success_q_choice`` / ``success_mean_pose``, ``return`` (the held-out
    episodes' mean return from the pose Q prefers), ``choice_raises_q`` (the fraction of
    held-out start states on which ``select_camera`` ends above Q at the default pose) and
    ``choice_q_gain`` (its mean gain in Q), ``wall_s``.
    """
    c = config
    if restore is not None:
        raise ValueError("sensing cannot resume; run it again without --resume")
    if not hasattr(env, "mount") or not hasattr(env, "render"):
        raise SensingError(f"sensing needs a task with a camera mount; {env.name} has none")
    if actor is None:
        if not c.actor:
            raise SensingError("sensing needs the image actor: --set actor=DIR (a twinrl train "
                             "--algo imitation --set observation=pixels run)")
        net, params, _ = load_actor(c.actor)
        actor = (net, params)
    actor_net, actor_params = actor
    if actor_net.out_size != env.action_size:
        raise SensingError(f"the actor outputs {actor_net.out_size} actions; {env.name} takes "
                           f"{env.action_size}")
    log = MetricLog()                      # its clock is the row's wall_s
    key = raw_key(rng)
    k_states, k_cams, k_init, k_fit = jax.random.split(key, 4)
    held = max(1, int(c.states) // 5)
    S = int(c.states) + held
    keys = jax.random.split(k_states, S)
    coords = uniform_coords(env.mount, k_cams, (S, int(c.cameras)))
    data = sensing_data(env, actor_net, actor_params, c, keys, coords)
    train_part = SensingData(*(jax.tree_util.tree_map(lambda x: x[:-held], f) for f in data))
    test_part = SensingData(*(jax.tree_util.tree_map(lambda x: x[-held:], f) for f in data))
    q = make_q(actor_net, env.action_size, c)
    q_params, losses = fit_q(q, q.init(k_init), train_part, c, k_fit)
    figures = evaluate_ranking(q, q_params, test_part)
    # the camera choice on the held-out start states: does the ascent raise Q above the default?
    choose = jax.jit(lambda s, k: select_camera(env, q, q_params, actor_net, actor_params, s, k,
                                                c))
    reset = jax.jit(env.reset)
    gains = []
    for i, k in enumerate(jax.random.split(k_fit, held)):
        sel = choose(reset(keys[S - held + i]), k)
        gains.append(float(sel.value) - float(sel.default_value))
    gains = np.asarray(gains)
    row = log.record(epoch=0, pairs=int(train_part.targets.size),
                     loss=float(np.mean(np.asarray(losses)[-max(1, int(c.fit_steps) // 10):])),
                     **figures, choice_raises_q=float(np.mean(gains > 0)),
                     choice_q_gain=float(np.mean(gains)))
    if progress_fn is not None:
        progress_fn(0, row)
    return q, q_params, log.as_dict()
