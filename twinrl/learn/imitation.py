"""An actor that imitates trajectory optimisation: behaviour cloning with DAgger (SAM-RL's actor).

SAM-RL (Lv et al., RSS 2023, Sec. 4.2) learns its actor by imitating the trajectories that the
differentiable simulator optimised. Plain behaviour cloning on those demonstrations drifts: the
actor's small errors take it to states no demonstration visited, where it has never been told what
to do (Ross, Gordon & Bagnell, "A reduction of imitation learning ... to no-regret online
learning", AISTATS 2011). The simulator is ours, so the expert can be asked there: **DAgger**.
Each round runs the actor from fresh start states, and every ``relabel_every``-th state it visits
is labelled by trajectory optimisation from that very state (``twinrl.learn.trajopt``, first
order with a line search, warm-started from the actor's own remaining actions, so the label is
the actor's plan improved by the simulator's gradient); the labels join the data set and the actor
is refitted on all of it. With ``solved_labels`` only the labels whose improved plan solves the
task are kept (spatula: 66-96 % of them per round; the filtered run reached 90 %).

Demonstrations: reset keys and optimised actions (``<task>_plans.npz``), the solved ones re-run.

Observations (``ImitationConfig.observation``):

- ``"state"``: the task's privileged observation vector;
- ``"pixels"``: what the robot would have -- ``{"state": joint angles and velocities,
  "pixels/mount": image}`` (``image_size`` square; RGB, depth in metres, the task's target mask)
  from the camera mount at a pose drawn per episode uniformly over the mount's workspace
  (``camera="random"``) or at its default pose (``camera="default"``); rendered by
  ``twinrl.render`` (arm tasks: ``ArmTask.render``);
- ``"target"``: the same image reduced to what its depth and target mask say of the target (the
  mean and spread of its back-projected points and its pixel count, ``arm.base.target_cloud``),
  with the tool point of the measured joints and the cloud's mean minus it: an MLP, not a CNN
  (on 2 CPU cores a CNN cloned 49 demonstrations to 10-20 % success in 7-25 minutes);
- ``"pose"``: the privileged observation's layout of the joints and the target's pose fitted to
  that cloud (``ArmTask.fit_target_pose``: to 1 mm where the cloud's mean is 2-3 cm off); only
  the views whose estimate is right (``accurate``) are cloned.

With ``views > 1`` every demonstration is rendered from that many mount poses (one pose per
demonstration teaches nothing about the others). ``train`` follows the trainers' contract,
``(policy, params, metrics)``; metrics per round: data size, fit loss, the actor's success and
return on ``eval_episodes`` fresh starts."""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.learn.augment import image_augment
from twinrl.learn.common import JSONConfig, MetricLog, make_minibatch_fit, make_optimizer, raw_key
from twinrl.learn.imitation_data import (PROPRIO, actor_episodes,  # noqa: F401 (re-exported)
                                         demonstration_data, episode_coords, make_observer,
                                         views_per_state)
from twinrl.learn.networks import NetworkConfig, make_network
from twinrl.learn.plans import (DemonstrationError, Demonstrations, accurate,
                                load_demonstrations, relabel)

__all__ = ["ImitationConfig", "Demonstrations", "DemonstrationError", "load_demonstrations",
           "demonstration_data", "accurate", "actor_episodes", "episode_coords", "label_weight",
           "make_observer", "relabel", "train"]


@dataclasses.dataclass(frozen=True)
class ImitationConfig(JSONConfig):
    demonstrations: str = ""
    """Path of a ``<task>_plans.npz`` (``twinrl train --algo imitation --set
    demonstrations=PATH``); ``train``'s ``demos`` argument takes precedence."""
    observation: str = "state"
    """``"state"``, ``"pixels"``, ``"target"`` or ``"pose"`` (module docstring)."""
    camera: str = "random"
    """Pixels: the mount pose per episode, ``"random"`` over its workspace or ``"default"``."""
    image_size: int | None = None
    """Image observations: their width and height; None: the task's, which the loop deploys at."""
    views: int = 1
    """Image observations: mount poses each demonstration is rendered from (module docstring)."""
    camera_input: bool | None = None
    """Image observations: the actor also sees the pose it commanded (``"camera"``), so it need
    not infer from the image where it looks from. Default (None): yes for ``"pixels"`` and
    ``"target"``, whose inputs are in the camera's frame; no for ``"pose"``, whose estimate is
    in the world's, where the pose only lets the actor tell views apart and learn each one's
    fit error: needle, 48 demonstrations x 8 views, the actor with it fed the *true* state
    succeeded on 18 % of 50 starts, without it on 94 % (60 % on its estimates either way)."""
    proprioception: bool | None = None
    """Image observations but ``"pose"``: the actor also reads the measured joint angles and
    velocities (14). Default (None): yes for ``"pixels"``, no for ``"target"``, whose tool point
    says where the tool is (spatula, README: with them 0 % on three real twins, without 0-30 %)."""
    image_head: str = "keypoints"
    """The CNN's head (``NetworkConfig.image_head``): ``"keypoints"`` or ``"dense"``."""
    conv_strides: tuple[int, ...] = (2, 2, 1)
    """The CNN's three strides: (2, 2, 1) leaves 16 x 16 keypoint maps of a 64 x 64 image."""
    rgb_jitter: float = 0.1
    """Pixels: RGB gain/offset jitter of each training image (``common.rgb_jitter``; 0: none)."""
    random_shift: int = 0
    """Pixels: each training image (behaviour cloning and every DAgger refit) shifted by up to
    this many pixels, edges repeated (DrQ, ``augment.random_shift``; 0: none). Off until
    measured: the loop's actors (``"pose"``, ``"target"``) see no image, and a CNN actor's fit
    (10,000 steps at 0.25 s) takes about 40 minutes on 2 cores."""
    hidden: tuple[int, ...] = (256, 256)
    learning_rate: float = 3e-4
    max_grad_norm: float | None = 1.0
    fit_steps: int = 10000
    """Adam steps per fit (of ``batch_size`` rows), after the demonstrations and each DAgger
    round. Peg's state actor, 46 demonstrations, 3 seeds x 50 starts: 1e-3 x 3,000 steps cloned
    to 85 +- 10 % success, 3e-4 x 10,000 to 97 +- 1 % (standardised inputs: 69 %)."""
    batch_size: int = 256
    dagger_rounds: int = 2
    dagger_episodes: int = 10
    """Actor episodes per DAgger round, from fresh start states."""
    relabel_every: int = 5
    """Label one in this many of the states the actor visits (trajopt per label is the cost)."""
    relabel_iterations: int = 10
    solved_labels: bool = False
    """DAgger keeps only the labels whose improved plan solves the task from that state (tasks
    with ``success``): the first action of a plan that fails is not an expert's."""
    label_weight: float | None = None
    """A DAgger label's weight in the fit, against a demonstration pair's 1. Default (None):
    ``views`` (1 for ``"state"``), so a visited state counts as much as a demonstrated one
    (spatula, README: 40 % unweighted, 80 % weighted)."""
    visit_noise: float = 0.0
    """DAgger's visits act with the actor's action plus smooth noise of this sd (6 knots over the
    episode, ``plans.smooth_noise``), so labels cover where a disturbance leads (DART: Laskey et
    al., CoRL 2017). 0: the actor's own actions."""
    step_size: float = 0.5
    """Trajopt's largest first-order step when labelling (``TrajoptConfig.step_size``)."""
    eval_episodes: int = 50
    keep: str = "best"
    """Which round's actor ``train`` returns: ``"best"``, the round with the highest success on
    the ``eval_episodes`` starts (then return; the latest on a tie), or ``"last"``. A refit on
    the grown data set can lose what the last one had (spatula twin 1's loop, 20 views: 10, 45,
    then 20 %); the simulator is ours, so the choice costs no real episode."""
    restarts: int = 1
    """Behaviour cloning from this many keys (the network's initialisation, the demonstrations'
    views, the minibatches; restart 0 is ``rng``'s own), the one with the highest success on the
    ``eval_episodes`` starts (then return) going on to DAgger. One fit varies far more than its
    data: peg twin 1's identified twin, 48 demonstrations x 8 views, three seeds scored on the
    same 50 other starts: 94, 78 and 50 % (20 stage starts: 95, 70, 40 %)."""

    def __post_init__(self):
        self.check_fields(
            at_least_one=("fit_steps", "batch_size", "relabel_every", "relabel_iterations",
                          "eval_episodes", "image_size", "dagger_episodes", "views",
                          "restarts"),
            non_negative=("dagger_rounds", "rgb_jitter", "label_weight", "visit_noise",
                          "random_shift"),
            widths=("hidden", "conv_strides"), optional=("label_weight", "image_size"),
            choices={"observation": ("state", "pixels", "target", "pose"),
                     "camera": ("random", "default"), "image_head": ("dense", "keypoints"),
                     "keep": ("best", "last"), "camera_input": (None, True, False),
                     "proprioception": (None, True, False)})
        if len(self.conv_strides) != 3:
            raise ValueError(f"conv_strides must name 3 strides, got {self.conv_strides}")


def label_weight(config: ImitationConfig) -> float:
    """A DAgger label's weight in the fit (``ImitationConfig.label_weight``)."""
    return float(views_per_state(config) if config.label_weight is None else config.label_weight)


def train(env, config: ImitationConfig = ImitationConfig(), rng: jax.Array | int = 0, *,
          demos: Demonstrations | None = None,
          progress_fn: Callable[[int, dict], None] | None = None, checkpoint_fn=None,
          restore=None, round_fn: Callable[[int, object], None] | None = None):
    """Behaviour cloning on ``demos`` (default: ``config.demonstrations``), then
    ``dagger_rounds`` DAgger rounds (module docstring). Not resumable: a round is minutes.

    Returns ``(policy, params, metrics)``: the actor ``Network`` (tanh output, actions in
    [-1, 1]), its parameters, and per round (``epoch``) ``pairs`` (data set size), ``loss``
    (the fit's mean squared action error), ``success`` and ``return`` of the actor on
    ``eval_episodes`` fresh start states, ``labels`` (expert labels added that round),
    ``labels_solved`` (the fraction of them whose improved plan solves the task; NaN in the
    last round, which labels nothing), ``clone_success_worst`` (round 0: the worst of the
    ``restarts`` clonings on the eval starts; the round's ``success`` is the best), ``wall_s``,
    ``kept`` (1 at the round whose actor is returned: ``ImitationConfig.keep``;
    ``runner.train_run`` reports that row as final).
    ``round_fn(round, params)``, if given, sees each round's actor (``bench/imitation.py``).
    """
    c = config
    if restore is not None:
        raise ValueError("imitation cannot resume; run it again without --resume")
    if demos is None:
        if not c.demonstrations:
            raise DemonstrationError("imitation needs demonstrations: --set demonstrations=PATH (a "
                             "<task>_plans.npz from bench/manipulation.py)")
        demos = load_demonstrations(c.demonstrations)
    if demos.actions.shape[1:] != (env.episode_length, env.action_size):
        raise DemonstrationError(f"demonstrations have shape {demos.actions.shape[1:]} per plan; "
                         f"{env.name} needs ({env.episode_length}, {env.action_size})")
    key = raw_key(rng)
    k_init, k_demo, k_eval, key = jax.random.split(key, 4)
    observe, spec = make_observer(env, c)
    net = make_network(spec, env.action_size, NetworkConfig(
        hidden=tuple(c.hidden), activation="elu", output="tanh", image_head=c.image_head,
        conv_strides=tuple(c.conv_strides)))
    tx = make_optimizer(c.learning_rate, c.max_grad_norm)
    T = env.episode_length
    picks = np.arange(0, T, int(c.relabel_every))
    per_round = int(c.dagger_episodes) * picks.size
    jitter = image_augment(c.rgb_jitter, c.random_shift) if c.observation == "pixels" else None
    fit = make_minibatch_fit(net.apply, tx, int(c.fit_steps), int(c.batch_size), jitter)
    episodes = lambda p, k, n, noise=0.0: actor_episodes(  # noqa: E731
        env, observe, lambda o: net.apply(p, o), c, k, n, noise)

    @jax.jit
    def evaluate(p, k):
        ep = episodes(p, k, c.eval_episodes)
        return jnp.mean(ep.rewards.sum(1)), jnp.mean(ep.success)

    def clone(k_init, k_demo, k_fit):
        """Behaviour cloning from one set of keys: the data set (grown to hold every DAgger
        round's labels), the fitted parameters and optimiser state, the fit's loss."""
        obs, acts, weights = demonstration_data(env, demos, c, k_demo)
        capacity = acts.shape[0] + int(c.dagger_rounds) * per_round
        grow = lambda x: jnp.concatenate(  # noqa: E731
            [x, jnp.zeros((capacity - x.shape[0],) + x.shape[1:], x.dtype)])
        data = (jax.tree_util.tree_map(grow, obs), grow(acts), acts.shape[0], grow(weights))
        params = net.init(k_init)
        params, opt, losses = fit(params, tx.init(params), data[0], data[1], data[2], k_fit,
                                  data[3])
        return data, params, opt, losses

    @jax.jit
    def visit_and_label(p, k):
        o, s, sent = episodes(p, k, c.dagger_episodes, float(c.visit_noise))[:3]
        sel = lambda x: x[:, picks].reshape((x.shape[0] * picks.size,) + x.shape[2:])  # noqa
        steps = jnp.arange(T)
        # warm start at step t: the actor's own actions from t on, zeros past the episode
        warm = jax.vmap(lambda a: jax.vmap(lambda t: jnp.where(
            (steps < T - t)[:, None], jnp.roll(a, -t, axis=0), 0.0))(jnp.asarray(picks)))(sent)
        states = jax.tree_util.tree_map(sel, s)
        left = jnp.tile(T - jnp.asarray(picks), sent.shape[0])
        labels, solved = relabel(env, states, warm.reshape((left.size, T, -1)), c, left)
        w = sel(accurate(o, s, env)) * (solved if c.solved_labels else 1.0) * label_weight(c)
        return jax.tree_util.tree_map(sel, o), labels, w, jnp.mean(solved)

    log, rounds = MetricLog(), []  # rounds: (success, return, round, params) of each round
    for r in range(int(c.dagger_rounds) + 1):
        key, k_fit, k_visit = jax.random.split(key, 3)
        if r == 0:  # cloning, from each restart's keys; the best on the eval starts goes on
            best, scores = None, []  # only the best's data set is kept (images are large)
            for i in range(int(c.restarts)):
                ks = (k_init, k_demo, k_fit) if i == 0 else jax.random.split(
                    jax.random.fold_in(k_init, i), 3)
                tried = clone(*ks)
                ret, ok = evaluate(tried[1], k_eval)
                scores.append((float(ok), float(ret), -i))
                if best is None or scores[-1] > max(scores[:-1]):  # the first on a tie
                    best = tried
            (obs, acts, n, weights), params, opt, losses = best
            ok, ret = max(scores)[:2]
        else:
            params, opt, losses = fit(params, opt, obs, acts, n, k_fit, weights)
            ret, ok = evaluate(params, k_eval)  # the same fresh states every round
        loss = jnp.mean(losses[-max(1, int(c.fit_steps) // 10):])
        added, solved = 0, float("nan")
        if r < int(c.dagger_rounds):
            new_obs, labels, new_w, solved = visit_and_label(params, k_visit)
            put = lambda buf, x: jax.lax.dynamic_update_slice_in_dim(buf, x, n, 0)  # noqa: E731
            obs = jax.tree_util.tree_map(put, obs, new_obs)
            weights = put(weights, new_w)
            acts, n, added = put(acts, labels), n + per_round, per_round
        row = log.record(epoch=r, pairs=n - added, loss=loss, success=ok, **{"return": ret},
                         labels=added, labels_solved=solved,
                         clone_success_worst=min(x[0] for x in scores) if r == 0 else float("nan"))
        rounds.append((float(ok), float(ret), r, params))
        if round_fn is not None:
            round_fn(r, params)
        if progress_fn is not None:
            progress_fn(r, row)
    kept = max(rounds, key=lambda x: x[:3]) if c.keep == "best" else rounds[-1]
    metrics = log.as_dict()
    metrics["kept"] = [float(r == kept[2]) for r in range(len(rounds))]
    return net, kept[3], metrics
