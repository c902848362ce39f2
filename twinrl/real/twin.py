"""``RealTwin``: a task's stand-in for the physical robot, as a ``gymnasium.Env``.

The loop (Real2Sim -> Learn@Sim -> Sim2Real, ``twinrl.loop``) needs a "real" system whose dynamics
and camera the simulator does not know exactly. ``RealTwin`` is the same task (same reset distribution, observation and reward
functions, from ``twinrl.envs``) run on a *different engine*: the MuJoCo C engine (``mj_step``,
float64, implicit-fast integration, 50 solver iterations by default) instead of MJX with a
fixed-iteration solve, with a hidden ``Perturbation`` applied: scaled masses, damping, friction and
motor gain, unmodeled extras (rail friction on the cartpole), action latency, Gaussian observation
noise, and cameras mounted off their nominal poses. So Real2Sim has something to identify and
Sim2Real has a gap to close (the "reality gap" of SAM-RL, Sec. 3, and of the Hybrid
Differentiable Simulation study's cartpole).

Images come from ``mujoco.Renderer`` headless (``twinrl.render.opengl.CameraRenderer``, re-exported
here; ``MUJOCO_GL=egl``, OSMesa if EGL cannot start): RGB, depth in metres (linear, distance along the camera's viewing axis; background pixels hold
the far-plane distance) and segmentation (geom id per pixel, -1 for background), seen from the
cameras' *true* (offset) poses.

What is hidden stays hidden: the perturbation, the true parameters and the true state are
returned only by ``oracle()``, for evaluation. Learning code must not call it (a test greps the
package, allowing only ``twinrl/real/`` and the evaluation/report modules).

``render_episode`` writes PNGs (RGB, depth, segmentation) and an MP4 of an episode, of the
simulator or the real twin, for the ``twinrl render`` command.
"""

from __future__ import annotations

import os

# Headless OpenGL for mujoco.Renderer. MuJoCo reads MUJOCO_GL when it is first imported, so this
# only takes effect if nothing imported mujoco before; ``twinrl.render.opengl`` covers the rest.
os.environ.setdefault("MUJOCO_GL", "egl")

import collections  # noqa: E402
import copy  # noqa: E402
import dataclasses  # noqa: E402
import functools  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any, Mapping, Sequence  # noqa: E402

import gymnasium as gym  # noqa: E402
import jax  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from twinrl.envs import Env, make  # noqa: E402
from twinrl.physics import PhysParams, load_mjcf, mujoco_warnings  # noqa: E402
from twinrl.real.perturbation import Perturbation, rotvec_quat  # noqa: E402
from twinrl.render.opengl import IMAGE_KINDS, CameraRenderer, render_states  # noqa: E402,F401

__all__ = ["make_real", "RealTwin", "Oracle", "CameraRenderer", "render_episode", "render_states",
           "IMAGE_KINDS", "reset_key"]

_INTEGRATORS = {
    "euler": mujoco.mjtIntegrator.mjINT_EULER,
    "implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST,
    "implicit": mujoco.mjtIntegrator.mjINT_IMPLICIT,
    "rk4": mujoco.mjtIntegrator.mjINT_RK4,
}


# ---------------------------------------------------------------------- the real twin
@dataclasses.dataclass(frozen=True)
class Oracle:
    """What the real twin hides, for evaluation only (see ``RealTwin.oracle``)."""

    perturbation: Perturbation
    params: PhysParams
    """The true physical parameters (the simulator's ``PhysParams`` fields, perturbed)."""
    model: mujoco.MjModel
    """A copy of the real twin's model (true parameters and camera poses, engine settings)."""
    qpos: np.ndarray
    """The true (noise-free) state now."""
    qvel: np.ndarray


def _task(name: str, config: dict) -> tuple[Env, tuple]:
    """``make(name, **config)`` and its ``initial_state``, ``observe``, ``reward``, ``control``
    and ``success`` (None without one), jitted. Shared by the twins of one (name, config) in a
    process (tasks are immutable; the last 16 kept) so they compile these once, not per twin;
    a config whose values are not hashable gets its own."""
    try:
        key = (name, tuple(sorted(config.items())))
        hash(key)
    except TypeError:
        return _make_jitted(make(name, **config))
    return _jitted(name, key[1])


def _make_jitted(task: Env) -> tuple[Env, tuple]:
    success = jax.jit(task.success) if hasattr(task, "success") else None
    return task, (jax.jit(task.initial_state), jax.jit(task.observe), jax.jit(task.reward),
                  jax.jit(task.control), success)


@functools.lru_cache(maxsize=16)
def _jitted(name: str, items: tuple) -> tuple[Env, tuple]:
    return _make_jitted(make(name, **dict(items)))


class RealTwin(gym.Env):
    """A registered task on the MuJoCo C engine with a hidden perturbation.

    Args:
      task: registered task name (``twinrl.envs.names()``), or a task itself (an ``Env``: your
        MJCF's, ``twinrl.envs.from_mjcf(path, reward=...)``, so your robot gets a real twin to
        test a pipeline on before the robot: MuJoCo C, the default ``PerturbationSpec``'s hidden
        draw or your ``perturbation``; its camera is the MJCF's first, else where MuJoCo's
        viewer opens). ``config`` is for task names only.
      seed: picks the hidden perturbation (unless given) and seeds episodes until ``reset`` is
        given a seed of its own.
      perturbation: the ``Perturbation`` to apply; default ``Perturbation.sample(task, seed)``;
        ``Perturbation.none()`` makes the twin match the simulator up to the engines.
      render_mode: ``None`` or ``"rgb_array"`` (``render()`` returns the default camera's RGB).
      width, height: image size of ``render``/``render_images``.
      shadows: shadow mapping in ``render``/``render_images`` (MuJoCo's default, on), its map
        sized to the image (``CameraRenderer``'s ``shadow_size``: 1024^2 up to 256-pixel frames,
        not the scene's 2048-4096^2; a 64x64 frame 2-5x faster in software OpenGL). Off is
        faster still (videos); images fitted against should keep the default.
      config: task config overrides (as for ``twinrl.envs.make``).
      integrator: MuJoCo integrator of the real engine (``implicitfast``, ``rk4``, ``euler``,
        ``implicit``).
      iterations: constraint-solver iterations of the real engine (MuJoCo C stops at convergence).
      substeps: real physics steps per simulator physics step (the real timestep is the scene's
        divided by this).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init__(
        self,
        task: str,
        *,
        seed: int = 0,
        perturbation: Perturbation | None = None,
        render_mode: str | None = None,
        width: int = 320,
        height: int = 240,
        shadows: bool = True,
        config: Mapping[str, Any] | None = None,
        integrator: str = "implicitfast",
        iterations: int = 50,
        substeps: int = 1,
    ):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if integrator not in _INTEGRATORS:
            raise ValueError(f"integrator must be one of {list(_INTEGRATORS)}, got {integrator!r}")
        if int(substeps) < 1 or int(iterations) < 1:
            raise ValueError(f"substeps and iterations must be >= 1, got {substeps}, {iterations}")
        self.task: Env
        if isinstance(task, Env):
            if config:
                raise ValueError("config overrides are for a task name; give the Env built with "
                                 "them")
            self.task, fns = _make_jitted(task)
            self.task_name = task.name
        elif isinstance(task, str):
            self.task, fns = _task(task, dict(config or {}))
            self.task_name = task
        else:
            raise TypeError(f"task must be a task name or a twinrl.envs.Env, got "
                            f"{type(task).__name__}")
        if not isinstance(seed, (int, np.integer)) or int(seed) < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        self.seed = int(seed)
        rngs = np.random.SeedSequence(self.seed).spawn(2)
        if perturbation is None:
            perturbation = Perturbation.sample(self.task, np.random.default_rng(rngs[0]))
        if not isinstance(perturbation, Perturbation):
            raise TypeError(f"perturbation must be a Perturbation or None, got {perturbation!r}")
        self._perturbation = perturbation

        model = load_mjcf(self.task.mjcf())
        model.opt.integrator = _INTEGRATORS[integrator]
        model.opt.iterations = int(iterations)
        model.opt.ls_iterations = max(int(model.opt.ls_iterations), int(iterations))
        model.opt.timestep = model.opt.timestep / int(substeps)
        perturbation.apply(model)
        self._model = model
        self._data = mujoco.MjData(model)
        # for ``success``: the tool body, and kinematics scratch of the nominal and real models
        self._tool_body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "tool")
        self._scratch = (mujoco.MjData(self.task.sim.mj_model), mujoco.MjData(model))
        self._n_physics = int(self.task.config.frame_skip) * int(substeps)

        # The task's own functions (JAX, jitted once per task and config in a process, shared by
        # its twins) so sim and real observe and reward alike.
        self._initial_state, self._observe, self._reward, self._control, self._success = fns
        self._controls = {None: self._control}
        self.joint_speed = None
        """The Cartesian controller's calibration (``calibrate_controller``); None: nominal."""

        nu = self.task.action_size
        obs_size = self.task.observation_size
        self.action_space = gym.spaces.Box(-1.0, 1.0, (nu,), np.float32)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (obs_size,), np.float32)
        self.render_mode = render_mode
        self.metadata = {**type(self).metadata, "render_fps": int(round(1.0 / self.task.dt))}
        self.width, self.height = int(width), int(height)
        self.shadows = bool(shadows)
        self.camera = self.task.default_camera
        """The default camera (``Env.default_camera``)."""
        self._renderer: CameraRenderer | None = None
        self._np_random = np.random.default_rng(rngs[1])
        self._pending: collections.deque = collections.deque()
        self._t = 0
        self.camera_steps = 0
        """Control steps spent moving the camera mount (``move_camera``) since construction."""
        self._mount = getattr(self.task, "mount", None)
        self._mount_coords = None
        if self._mount is not None:
            self.move_camera(self._mount.default)
            self.camera_steps = 0

    # ------------------------------------------------------------------ gymnasium API
    @property
    def dt(self) -> float:
        return self.task.dt

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        key = _reset_key(self.np_random)
        qpos, qvel = (np.asarray(x, np.float64) for x in self._initial_state(key))
        options = dict(options or {})
        for name, default in (("qpos", qpos), ("qvel", qvel)):
            if name in options:  # start from a given state (e.g. a simulator's, to compare)
                v = np.asarray(options.pop(name), np.float64)
                if v.shape != default.shape or not np.all(np.isfinite(v)):
                    raise ValueError(
                        f"options[{name!r}] must be {default.shape} finite numbers, got {v!r}"
                    )
                qpos, qvel = (v, qvel) if name == "qpos" else (qpos, v)
        if options:
            raise ValueError(f"unknown reset option(s) {sorted(options)}; allowed: qpos, qvel")
        mujoco.mj_resetData(self._model, self._data)
        self._data.qpos[:] = qpos
        self._data.qvel[:] = qvel
        mujoco.mj_forward(self._model, self._data)
        zero = np.zeros(self.action_space.shape, np.float32)
        self._pending = collections.deque([zero] * self._perturbation.latency_steps)
        self._t = 0
        return self._observation(), {}

    def step(self, action):
        a = np.asarray(action, dtype=np.float32)
        if a.shape != self.action_space.shape or not np.all(np.isfinite(a)):
            raise ValueError(
                f"action must be {self.action_space.shape} finite numbers in [-1, 1],"
                f" got {action!r}"
            )
        a = np.clip(a, -1.0, 1.0)
        self._pending.append(a)
        applied = self._pending.popleft()
        d = self._data
        self._data.ctrl[:] = np.asarray(self._control(d.qpos, d.qvel, applied), np.float64)
        with mujoco_warnings(f"the {self.task.name} real twin"):
            mujoco.mj_step(self._model, self._data, nstep=self._n_physics)
        self._t += 1
        d = self._data
        reward, terms = self._reward(d.qpos, d.qvel, a)
        terminated = not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel)))
        truncated = self._t >= self.task.episode_length
        info = {f"reward/{k}": float(v) for k, v in terms.items()}
        return self._observation(), float(reward), bool(terminated), bool(truncated), info

    def _observation(self) -> np.ndarray:
        obs = np.asarray(self._observe(self._data.qpos, self._data.qvel), np.float32)
        std = self._perturbation.obs_noise_std
        if std > 0:
            obs = obs + self.np_random.normal(0.0, std, size=obs.shape).astype(np.float32)
        return obs

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("RealTwin.render() called without render_mode='rgb_array'")
            return None
        return self.render_images(kinds=("rgb",))["rgb"]

    def render_images(
        self, camera: str | None = None, kinds: Sequence[str] = IMAGE_KINDS
    ) -> dict[str, np.ndarray]:
        """RGB, depth (m) and segmentation (geom ids) from ``camera``'s true (offset) pose."""
        if self._renderer is None:
            self._renderer = CameraRenderer(self._model, self.width, self.height,
                                            shadows=self.shadows)
        return self._renderer.images(self._data, camera or self.camera, kinds)

    def calibrate_controller(self, joint_speed=None) -> None:
        """Configure the arm's Cartesian controller with each servo's speed relative to the
        nominal arm's (``ArmTask.calibrate_controller``; None: uncalibrated), as a robot's
        Cartesian interface is configured: from the next step on, the targets it sets are
        divided joint by joint. The identified twin's value (``System.controller``);
        ``Deployer.run`` sets it from its task. The twin's true servos are untouched."""
        from twinrl.envs.arm.controller import check_joint_speed

        if getattr(self.task, "controller", None) is None:
            if joint_speed is None:
                return
            raise ValueError(f"task {self.task_name!r} has no Cartesian controller to calibrate")
        js = check_joint_speed(joint_speed)
        if js not in self._controls:
            task = copy.copy(self.task)
            task.calibrate_controller(js)
            self._controls[js] = jax.jit(task.control)
        self._control, self.joint_speed = self._controls[js], js

    def move_camera(self, coords) -> int:
        """Move the task's camera mount (arm tasks: ``task.mount``) to unconstrained mount
        coordinates ``coords`` (3,) and return the control steps the move takes at the mount's
        speed limit (also added to ``camera_steps``). The camera lands at the commanded pose
        composed with the hidden hand-eye offset (the perturbation's camera offsets, in the
        camera's frame), as a camera on a robot's hand does."""
        if self._mount is None:
            raise ValueError(f"task {self.task_name!r} has no camera mount; its cameras are fixed: "
                             f"{list(self.task.cameras)}")
        c = np.asarray(coords, np.float64)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise ValueError(f"camera mount coordinates must be 3 finite numbers, got {coords!r}")
        mount, p = self._mount, self._perturbation
        steps = 0 if self._mount_coords is None else mount.steps_to_move(self._mount_coords, c)
        eye = np.asarray(mount.eye(jax.numpy.asarray(c)), np.float64)
        R = np.asarray(mount.xmat(jax.numpy.asarray(c)), np.float64)
        off = np.empty(9)
        mujoco.mju_quat2Mat(off, rotvec_quat(p.camera_rot_offset))
        R_true = R @ off.reshape(3, 3)
        cid = mujoco.mj_name2id(self._model, mujoco.mjtObj.mjOBJ_CAMERA, "mount")
        self._model.cam_pos[cid] = eye + R @ np.asarray(p.camera_pos_offset, np.float64)
        q = np.empty(4)
        mujoco.mju_mat2Quat(q, R_true.reshape(-1))
        self._model.cam_quat[cid] = q
        self._model.cam_fovy[cid] = mount.fovy
        mujoco.mj_camlight(self._model, self._data)  # the data's camera frame, from the new pose
        self._mount_coords = c
        self.camera_steps += steps
        return steps

    def success(self) -> float:
        """The task's success of the true state now (evaluation only, like ``oracle``). An arm
        task's is judged at its *true* tool: the controller's tool centre point carried by the
        real engine's ``tool`` body, the hidden grasp offset included -- not at the nominal
        kinematics the robot believes in."""
        task = self.task
        if not hasattr(task, "success"):
            raise ValueError(f"task {self.task_name!r} has no success measure")
        jnp = jax.numpy
        q, v = (jnp.asarray(x, jnp.float32) for x in (self._data.qpos, self._data.qvel))
        tool = self.true_tool()
        if tool is None:
            return float(self._success(q, v))
        return float(self._success(q, v, tuple(jnp.asarray(x, jnp.float32) for x in tool)))

    def true_tool(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The true tool point now, ``(position (3,), rotation (3, 3))`` in the world: the
        controller's tool centre point carried by the real engine's ``tool`` body, the hidden
        grasp offset included (evaluation only, like ``oracle``; None for a task without a
        tool)."""
        task, tool = self.task, self._tool_body
        if tool < 0 or not hasattr(task, "controller"):
            return None
        from twinrl.envs.arm.kinematics import forward_kinematics

        jnp = jax.numpy
        frames = []
        for model, d in ((self.task.sim.mj_model, self._scratch[0]), (self._model,
                                                                      self._scratch[1])):
            d.qpos[:] = self._data.qpos
            mujoco.mj_kinematics(model, d)
            frames.append((d.xpos[tool].copy(), d.xmat[tool].reshape(3, 3).copy()))
        (pn, Rn), (pt, Rt) = frames
        tip, R = (np.asarray(x, np.float64) for x in forward_kinematics(
            jnp.asarray(self._data.qpos[:7], jnp.float32), task.controller.tcp))
        true_tip = pt + Rt @ (Rn.T @ (tip - pn))  # the nominal point, carried by the true tool
        return true_tip, Rt @ Rn.T @ R

    @property
    def mount_coords(self) -> np.ndarray | None:
        """The camera mount's commanded coordinates (``move_camera``'s last; None without a
        mount): what the robot knows of where its camera is (the hand-eye offset it does not)."""
        return None if self._mount_coords is None else self._mount_coords.copy()

    def nominal_camera(self, camera: str | None = None) -> dict[str, np.ndarray | float]:
        """A camera's *nominal* pose (from the task's MJCF) and intrinsics: ``pos`` (3,) and
        ``xmat`` (3, 3) in the world frame, ``fovy`` (deg), ``width``, ``height``."""
        if self._mount is not None and (camera or self.camera) == "mount":
            # a camera mount's nominal pose is the commanded one (without the hand-eye offset)
            c = jax.numpy.asarray(self._mount_coords)
            return {"pos": np.asarray(self._mount.eye(c), np.float64),
                    "xmat": np.asarray(self._mount.xmat(c), np.float64),
                    "fovy": float(self._mount.fovy), "width": self.width, "height": self.height}
        m = self.task.sim.mj_model
        d = mujoco.MjData(m)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_camlight(m, d)
        cam = camera or self.camera
        cid = (int(cam) if isinstance(cam, (int, np.integer))
               else mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_CAMERA, cam))
        if cid < 0 or cid >= m.ncam:
            raise ValueError(f"camera {cam!r} is not in scene {self.task.scene!r}" + (
                " (-1, MuJoCo's free camera, has no pose in the MJCF: add a <camera>)"
                if cam == -1 else ""))
        return {
            "pos": d.cam_xpos[cid].copy(),
            "xmat": d.cam_xmat[cid].reshape(3, 3).copy(),
            "fovy": float(m.cam_fovy[cid]),
            "width": self.width,
            "height": self.height,
        }

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # ------------------------------------------------------------------ evaluation only
    def oracle(self) -> Oracle:
        """The hidden truth: perturbation, true parameters, true model and state. For evaluation
        and tests only; learning code must not call this (enforced by a test)."""
        return Oracle(
            perturbation=self._perturbation,
            params=PhysParams.from_model(self._model),
            model=copy.deepcopy(self._model),
            qpos=self._data.qpos.copy(),
            qvel=self._data.qvel.copy(),
        )


def _reset_key(rng: np.random.Generator) -> jax.Array:
    return jax.random.PRNGKey(int(rng.integers(0, 2**31 - 1)))


def reset_key(seed: int) -> jax.Array:
    """The key ``RealTwin.reset(seed=seed)`` draws its start from (``task.initial_state(key)``):
    ``env.reset(reset_key(seed))`` starts a simulator where that real episode starts, for
    comparing the two from the same state (the start's qpos is the same computation, in float32
    here and float64 there)."""
    return _reset_key(np.random.default_rng(int(seed)))


# ---------------------------------------------------------------------- recording
def make_real(name: str, *, seed: int = 0, perturbation: Perturbation | None = None,
              **kwargs: Any) -> RealTwin:
    """The real twin of task ``name`` (a ``RealTwin``, a ``gymnasium.Env``).

    Args:
      seed: selects the hidden perturbation (when ``perturbation`` is None) and the default
        episode seed.
      perturbation: a ``Perturbation`` (``Perturbation.none()`` for an exact twin); default:
        drawn from the task's ``perturbation_spec`` with ``seed``.
      kwargs: passed to ``RealTwin`` (``render_mode``, ``width``, ``height``, config overrides
        as ``config={...}``, engine settings).
    """
    return RealTwin(name, seed=seed, perturbation=perturbation, **kwargs)


# ---------------------------------------------------------------------- episodes to files
def _smooth_actions(steps: int, nu: int, dt: float, seed: int) -> np.ndarray:
    """Open-loop demo actions: ``0.8 cos(2 pi f t)`` per actuator, ``f`` in [0.4, 0.9] Hz from
    ``seed``. A cosine starting at its peak has a zero-mean integral, so a cart or pusher driven
    by it oscillates in view instead of drifting off."""
    f = np.random.default_rng(seed).uniform(0.4, 0.9, size=nu)
    t = np.arange(steps)[:, None] * dt
    return (0.8 * np.cos(2 * np.pi * f * t)).astype(np.float32)


def _colorize_depth(depth: np.ndarray, far: float) -> np.ndarray:
    import matplotlib

    valid = depth < 0.999 * far
    lo, hi = (depth[valid].min(), depth[valid].max()) if valid.any() else (0.0, 1.0)
    x = np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1)
    rgb = (matplotlib.colormaps["viridis"](x)[..., :3] * 255).astype(np.uint8)
    rgb[~valid] = 0
    return rgb


def _colorize_segmentation(seg: np.ndarray) -> np.ndarray:
    palette = (np.random.default_rng(0).uniform(60, 255, size=(256, 3))).astype(np.uint8)
    rgb = palette[np.mod(seg, 256)]
    rgb[seg < 0] = 0
    return rgb


def render_episode(
    name: str,
    real: bool = True,
    seed: int = 0,
    out_dir: str | os.PathLike = ".",
    steps: int = 100,
    width: int = 320,
    height: int = 240,
    camera: str | None = None,
) -> dict[str, Path]:
    """Roll out smooth open-loop actions (from ``seed``) on task ``name`` and write images.

    ``real=True`` runs the real twin (default perturbation for ``seed``, camera at its true,
    offset pose); ``real=False`` the MJX simulator, rendered at the nominal camera pose.
    Writes ``<name>_<real|sim>_{rgb,depth,segmentation}.png`` (last frame; depth colour-mapped
    viridis, near=purple, far=yellow, background black; segmentation one colour per geom) and
    ``<name>_<real|sim>.mp4`` (``.gif`` if no ffmpeg). Returns those paths by kind
    (``rgb``, ``depth``, ``segmentation``, ``video``).
    """
    import imageio.v2 as imageio

    if int(steps) < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    twin = RealTwin(
        name,
        seed=seed,
        perturbation=None if real else Perturbation.none(),
        width=width,
        height=height,
    )
    camera = camera or twin.camera
    actions = _smooth_actions(int(steps), twin.action_space.shape[0], twin.dt, seed)
    frames: list[np.ndarray] = []
    try:
        if real:
            twin.reset(seed=seed)
            for a in actions:
                twin.step(a)
                frames.append(twin.render_images(camera, ("rgb",))["rgb"])
            last = twin.render_images(camera)
        else:  # the simulator's states, drawn with the nominal model
            env = twin.task
            state, step = jax.jit(env.reset)(jax.random.PRNGKey(seed)), jax.jit(env.step)
            # the unperturbed twin's model: the nominal one, its camera mount (if any) in place
            m = twin._model
            d = mujoco.MjData(m)
            renderer = CameraRenderer(m, width, height)
            try:
                for a in actions:
                    state = step(state, a)
                    d.qpos[:] = np.asarray(state.pipeline_state.qpos)
                    mujoco.mj_forward(m, d)
                    frames.append(renderer.images(d, camera, ("rgb",))["rgb"])
                last = renderer.images(d, camera)
            finally:
                renderer.close()
    finally:
        twin.close()

    # a file name: "dmc/walker-walk" -> "dmc_walker-walk" (the Control Suite's names hold a slash)
    tag = f"{name.replace('/', '_')}_{'real' if real else 'sim'}"
    far = float(twin._model.vis.map.zfar * twin._model.stat.extent)
    paths = {
        "rgb": out / f"{tag}_rgb.png",
        "depth": out / f"{tag}_depth.png",
        "segmentation": out / f"{tag}_segmentation.png",
    }
    imageio.imwrite(paths["rgb"], last["rgb"])
    imageio.imwrite(paths["depth"], _colorize_depth(last["depth"], far))
    imageio.imwrite(paths["segmentation"], _colorize_segmentation(last["segmentation"]))
    fps = int(round(1.0 / twin.dt))
    try:
        paths["video"] = out / f"{tag}.mp4"
        imageio.mimsave(paths["video"], frames, fps=fps, macro_block_size=1)
    except Exception:  # noqa: BLE001 - no ffmpeg backend: fall back to GIF
        paths["video"] = out / f"{tag}.gif"
        imageio.mimsave(paths["video"], frames, duration=1000.0 / fps)
    return paths
