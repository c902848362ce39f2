"""Deployment with active sensing on a real twin (SAM-RL's Sim2Real: Lv et al., RSS 2023, Sec. 4).

An episode on the real robot (here: a ``RealTwin``, MuJoCo C and its OpenGL camera):

1. read the start state off what the robot measures (``Env.state_from_obs`` of the twin's
   observation: joint encoders, and the objects' poses as its perception reports them, with the
   twin's observation noise) -- the *state estimate* the simulator renders candidate views of;
2. choose the camera pose (``camera``, below) and move the mount there
   (``RealTwin.move_camera``: the real camera lands at the commanded pose composed with the hidden
   hand-eye offset; the steps the move takes are counted, ``camera_steps``);
3. every step, take the real mount image (RGB, depth, and the target's mask from the real
   segmentation), and act with the image actor -- plus a residual policy's correction if one is
   given (``residual(obs, action) -> delta`` of the measured observation and the actor's action,
   added and clipped to [-1, 1]; ``residual_correction``);
4. re-choose the camera every ``reselect_every`` steps if asked (0: once per episode).

``camera``:

- ``"selected"``: gradient ascent of the sensing-aware Q through the differentiable renderer from
  the state estimate (``twinrl.learn.camera_choice.select_camera``);
- ``"default"``: the mount's fixed default pose (the fixed-camera baseline);
- ``"random"``: a pose drawn uniformly over the mount's workspace per episode;
- ``"oracle"``: no camera -- a *state* policy acting on the twin's privileged observation vector
  (the upper reference of the sensing benchmark, ``bench/sensing.py``).

Success is ``RealTwin.success``: the task's success of the twin's true final state, judged at the
true tool (grasp offset included) -- evaluation only, nothing here learns from it.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.learn.camera_choice import image_size, select_camera
from twinrl.learn.common import JSONConfig

__all__ = ["CAMERAS", "POSE_MEMORY", "DeployConfig", "PoseMemory", "real_image_observation",
           "sim_state", "Deployer", "deploy", "pose_actor_on_state", "residual_correction"]

CAMERAS = ("selected", "default", "random", "oracle")
POSE_MEMORY = ("none", "best")


@dataclasses.dataclass(frozen=True)
class DeployConfig(JSONConfig):
    camera: str = "selected"
    """``"selected"``, ``"default"``, ``"random"`` or ``"oracle"`` (module docstring)."""
    episodes: int = 50
    reselect_every: int = 0
    """Choose the camera again every this many steps (0: once, at the episode's start)."""
    restarts: int | None = None
    """Ascents per choice; None: the Q checkpoint's ``SensingConfig.restarts``."""
    ascent_steps: int | None = None
    smooth_samples: int | None = None
    """Poses around each leading candidate its Q is averaged over (0: the pose alone); None:
    the Q checkpoint's ``SensingConfig.smooth_samples``."""
    pose_memory: str = "none"
    """A ``"pose"`` actor's target pose (the target is at rest): ``"none"``, each frame's own
    fit; ``"best"``, the fit of the frame with the most target pixels so far this episode (the
    least occluded, nearest view), its estimate rebuilt with each step's joints. Other actors
    ignore it."""

    def __post_init__(self):
        self.check_fields(at_least_one=("episodes", "restarts", "ascent_steps"),
                          non_negative=("reselect_every", "smooth_samples"),
                          choices={"camera": CAMERAS, "pose_memory": POSE_MEMORY},
                          optional=("restarts", "ascent_steps", "smooth_samples"))


def real_image_observation(twin, env, obs: np.ndarray, size: int, img: dict | None = None,
                           keys: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """The image actor's observation on the real twin: ``ArmTask.observation_from_image`` of the
    real OpenGL frame -- RGB in [0, 1], depth (m), the target geoms' mask from the real
    segmentation -- with the joints measured (``obs[:14]``) and the *commanded* mount pose (the
    hand-eye offset is the robot's unknown, or what ``env.mount`` identified). ``twin`` must
    render ``size`` x ``size`` frames; ``img`` is the mount's frame when already taken;
    ``keys``: only these entries (an actor's ``obs_spec``), only their work done."""
    if (twin.width, twin.height) != (size, size):
        raise ValueError(f"the twin renders {twin.width}x{twin.height}; the actor needs "
                         f"{size}x{size} (make it with width=height={size})")
    img = twin.render_images(camera="mount") if img is None else img
    mask = np.isin(img["segmentation"], env.target_geom_ids).astype(np.float32)
    out = _from_image(env, None if keys is None else tuple(keys))(
        np.asarray(obs[:14], np.float32), np.asarray(twin.mount_coords, np.float32),
        img["rgb"].astype(np.float32) / 255.0, img["depth"].astype(np.float32), mask)
    return {k: np.asarray(v) for k, v in out.items()}


@functools.lru_cache(maxsize=None)
def _from_image(env, keys=None):
    """``env.observation_from_image`` (its ``keys`` only), jitted once per task and keys (it
    runs every real step)."""
    return jax.jit(lambda *a: env.observation_from_image(*a, keys=keys))


def sim_state(env, obs: jax.Array):
    """The simulator ``State`` of an observation (``Env.state_from_obs``): what the camera choice
    renders its candidate views of."""
    qpos, qvel = env.state_from_obs(jnp.asarray(obs, jnp.float32))
    data = env.sim.init(qpos, qvel)
    zero = jnp.zeros(())
    from brax.envs.base import State

    return State(pipeline_state=data, obs=env.observe(data.qpos, data.qvel), reward=zero,
                 done=zero, metrics={}, info={})


class Deployer:
    """Runs ``DeployConfig.episodes`` episodes on real twins (``run``); builds and jits the
    actor, the camera choice and the state estimate once, so several twins (seeds) and camera
    modes share them.

    Args:
      env: the simulator task (the identified twin, if any) the camera choice renders.
      actor, actor_params: the image actor (``observation="pixels"``), or for ``camera="oracle"``
        a state policy (``observation="state"``).
      q, q_params, sensing: the sensing-aware Q and its ``SensingConfig`` (``camera="selected"``).
      residual: optional ``residual(obs, action) -> delta``: a correction of the actor's action
        from the measured observation and that action, added (``residual_correction``).
    """

    def __init__(self, env, actor, actor_params, *, q=None, q_params=None, sensing=None,
                 residual: Callable | None = None):
        self.env, self.actor, self.actor_params = env, actor, actor_params
        self.q, self.q_params, self.sensing, self.residual = q, q_params, sensing, residual
        self.image = isinstance(actor.obs_spec, dict)
        self.size = image_size(env, actor) if self.image else 0
        self._act = jax.jit(actor.apply)
        self._state = jax.jit(lambda o: sim_state(env, o))
        self.pose = self.image and set(actor.obs_spec) == {"estimate"}  # a "pose" actor
        self._estimate = jax.jit(env.pose_estimate) if self.pose else None
        self._choose = {}

    def _chooser(self, restarts: int, steps: int, smooth: int | None = None):
        key = (restarts, steps, smooth)
        if key not in self._choose:
            cfg = dataclasses.replace(self.sensing, restarts=restarts, ascent_steps=steps)
            if smooth is not None:
                cfg = dataclasses.replace(cfg, smooth_samples=smooth)
            self._choose[key] = jax.jit(lambda s, k: select_camera(
                self.env, self.q, self.q_params, self.actor, self.actor_params, s, k, cfg))
        return self._choose[key]

    def check(self, config: DeployConfig) -> None:
        if config.camera == "oracle" and self.image:
            raise ValueError("camera='oracle' deploys a state policy; this actor sees images")
        if config.camera != "oracle" and not self.image:
            raise ValueError(f"camera={config.camera!r} needs an image actor "
                             f"(observation=pixels); this one sees the state vector")
        if config.camera == "selected" and self.q is None:
            raise ValueError("camera='selected' needs the sensing-aware Q (q, q_params, sensing)")

    def run(self, twin, config: DeployConfig, seed: int = 0, progress=None, *, start: int = 0,
            writer=None, on_episode: Callable[[dict], None] | None = None) -> dict:
        """Episodes ``start .. config.episodes - 1`` on ``twin`` (episode ``i`` resets with seed
        ``seed + i`` and draws its random choices from ``(seed, i)``, so a deployment resumed at
        ``start`` runs the episodes an uninterrupted one would have). Returns per-episode
        ``success``, ``return``, ``steps`` (control steps acting), ``camera_steps`` (steps spent
        moving the mount), ``choices`` (camera choices made), the chosen ``coords`` (first
        choice of each episode) and totals/means, ``wall_s``.

        ``writer`` (a ``twinrl.real.dataset.DatasetWriter`` recording ``rgb``, ``depth`` and
        ``segmentation``) records every transition as it happens, with the mount's frame after
        the step (the frame the next action sees); ``on_episode(row)`` gets each episode's row
        when it ends."""
        self.check(config)
        env, c = self.env, config
        if hasattr(twin, "calibrate_controller"):  # the robot's controller, as the twin's
            twin.calibrate_controller(getattr(getattr(env, "controller", None), "joint_speed",
                                              None))
        restarts = int(c.restarts or (self.sensing.restarts if self.sensing else 1))
        steps = int(c.ascent_steps or (self.sensing.ascent_steps if self.sensing else 1))
        rows = {k: [] for k in ("success", "return", "steps", "camera_steps", "choices")}
        coords_log = []
        kinds = ("rgb", "depth", "segmentation")
        t0 = time.perf_counter()
        for i in range(int(start), int(c.episodes)):
            rng = np.random.default_rng([int(seed), i])
            obs, _ = twin.reset(seed=int(seed) + i)
            before = twin.camera_steps
            choices, ret, first, img = 0, 0.0, None, None
            memory = PoseMemory() if self.pose and c.pose_memory == "best" else None
            for t in range(env.episode_length):
                if c.camera != "oracle" and (t == 0 or (c.reselect_every
                                                         and t % c.reselect_every == 0)):
                    coords = self._camera(c.camera, obs, rng, restarts, steps, c.smooth_samples)
                    twin.move_camera(coords)
                    choices += 1
                    first = coords if first is None else first
                    img = None
                if self.image and img is None:
                    img = twin.render_images("mount", kinds)
                o = (real_image_observation(twin, env, obs, self.size, img, ("pose", "support")
                                            if memory else tuple(self.actor.obs_spec))
                     if self.image else np.asarray(obs, np.float32))
                if memory is not None:
                    o = {"estimate": self._estimate(np.asarray(obs[:14], np.float32),
                                                    memory.update(o["pose"], o["support"][0]))}
                a = np.asarray(self._act(self.actor_params, o), np.float32)
                if self.residual is not None:
                    a = np.clip(a + np.asarray(self.residual(obs, a), np.float32), -1.0, 1.0)
                nxt, r, term, trunc, info = twin.step(a)
                img = (twin.render_images("mount", kinds)
                       if self.image or writer is not None else None)
                if writer is not None:
                    writer.add(obs, a, r, nxt, term, trunc or (t + 1 == env.episode_length),
                               info={k: v for k, v in info.items() if np.isscalar(v)},
                               images=img)
                obs, ret = nxt, ret + r
                if term:
                    break
            ok = twin.success()
            row = {"episode": i, "success": ok, "return": float(ret), "steps": t + 1,
                   "camera_steps": twin.camera_steps - before, "choices": choices,
                   "coords": None if first is None else np.asarray(first).tolist()}
            for k in rows:
                rows[k].append(row[k])
            coords_log.append(row["coords"])
            if on_episode is not None:
                on_episode(row)
            if progress is not None:
                progress(i + 1, {"success": float(np.mean(rows["success"])),
                                 "return": float(np.mean(rows["return"]))})
        out = {k: np.asarray(v).tolist() for k, v in rows.items()}
        out.update(coords=coords_log, camera=c.camera, seed=int(seed),
                   success_rate=float(np.mean(rows["success"])),
                   mean_return=float(np.mean(rows["return"])),
                   real_steps=int(np.sum(rows["steps"])),
                   real_camera_steps=int(np.sum(rows["camera_steps"])),
                   wall_s=time.perf_counter() - t0)
        return out

    def _camera(self, mode, obs, rng, restarts, steps, smooth=None) -> np.ndarray:
        mount = self.env.mount
        if mode == "default":
            return np.asarray(mount.default, np.float64)
        if mode == "random":
            u = rng.uniform(0.02, 0.98, 3)
            return np.log(u) - np.log1p(-u)
        state = self._state(jnp.asarray(obs, jnp.float32))
        key = jax.random.PRNGKey(int(rng.integers(0, 2**31 - 1)))
        return np.asarray(self._chooser(restarts, steps, smooth)(state, key).coords, np.float64)


class PoseMemory:
    """The target's pose fit kept over an episode (``DeployConfig.pose_memory="best"``): the
    fit of the frame with the most target pixels so far, the latest on a tie."""

    def __init__(self):
        self.pose, self.pixels = None, -np.inf

    def update(self, pose, pixels) -> np.ndarray:
        """Offer this frame's fit and its target pixel count; returns the pose kept."""
        if float(pixels) >= self.pixels:
            self.pose, self.pixels = np.asarray(pose), float(pixels)
        return self.pose


def deploy(env, twin, actor, actor_params, config: DeployConfig = DeployConfig(), *, seed=0,
           q=None, q_params=None, sensing=None, residual=None, progress=None) -> dict:
    """One-off ``Deployer(...).run(twin, config, seed)`` (see ``Deployer``)."""
    return Deployer(env, actor, actor_params, q=q, q_params=q_params, sensing=sensing,
                    residual=residual).run(twin, config, seed, progress)


def pose_actor_on_state(env, actor):
    """A ``"pose"`` image actor (``observation="pose"``: it reads ``{"estimate": ...}``) as a
    ``Network`` on the task's state observation, as perfect perception would feed it
    (``ArmTask.estimate_from_obs``): the base policy a residual is trained on through a model
    that renders no images (``twinrl.sim2real.residual``). Takes one observation or a batch."""
    from twinrl.learn.networks import Network

    if not isinstance(actor.obs_spec, dict) or set(actor.obs_spec) != {"estimate"}:
        raise ValueError(f"a residual on the state needs a 'pose' actor (it reads the pose "
                         f"estimate only); this one reads {sorted(actor.obs_spec or {})}")

    def apply(params, obs):
        obs = jnp.asarray(obs, jnp.float32)
        f = lambda o: actor.apply(params, {"estimate": env.estimate_from_obs(o)})  # noqa: E731
        for _ in range(obs.ndim - 1):
            f = jax.vmap(f)
        return f(obs)

    n = int(env.observation_size)
    return Network(actor.init, apply, n, actor.out_size, actor.config, n)


def residual_correction(delta, res_params) -> Callable:
    """``(obs, action) -> delta``: a trained residual's correction (``delta`` is
    ``ResidualPolicy.delta``, as its checkpoint holds it) of the measured observation and the
    deployed actor's action, jitted: the ``Deployer``'s ``residual``."""
    f = jax.jit(lambda o, a: delta.apply(res_params, jnp.concatenate([o, a], -1)))
    return lambda obs, a: np.asarray(f(jnp.asarray(obs, jnp.float32),
                                       jnp.asarray(a, jnp.float32)))
