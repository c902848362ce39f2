"""The arm tasks' ``Env``: ``ArmTask`` (the arm of ``panda.xml`` with a task's tool, scene,
Cartesian controller and camera mount), its ``ArmConfig``, and what the arm tasks' real twins
perturb (``ARM_PERTURBATIONS``). A task is built from an identified ``System`` (``with_system``:
the mount's hand-eye offset, the tool's grasp, the servos' speeds), drives the arm through its
controller, offers initial guesses for trajectory optimisation and a gradient-check scenario
through tool contact; its image side is ``perception.ArmPerception``."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.envs.arm.controller import CartesianController, check_joint_speed
from twinrl.envs.arm.kinematics import (N_JOINTS, TOOL_MOUNT, composed, forward_kinematics,
                                        joint_frames)
from twinrl.envs.arm.mount import CameraMount
from twinrl.envs.arm.perception import ArmPerception
from twinrl.envs.base import Env, PerturbationSpec, TaskConfig


ARM_PERTURBATIONS = PerturbationSpec(
    mass_scale=(0.9, 1.15), damping_scale=(0.8, 1.25), friction_scale=(0.7, 1.3),
    gain_scale=(0.85, 1.1), latency_steps=(0, 1), obs_noise_std=(0.0005, 0.002),
    camera_pos_std=0.01, camera_rot_std=0.02, tool_pos_std=0.003, tool_rot_std=0.03)
"""What the arm tasks' real twins perturb (each task adjusts it): link and object masses, joint
damping, friction, the servos' stiffness, latency, observation noise, the camera's hand-eye offset
(1 cm / 0.02 rad) and the tool's grasp in the hand (3 mm / 0.03 rad)."""


@dataclasses.dataclass(frozen=True)
class ArmConfig(TaskConfig):
    episode_length: int = 50
    """Control steps per episode (50 * 0.04 s = 2 s)."""
    frame_skip: int = 4
    """Physics steps (0.01 s) per control step: 25 Hz control, as Franka's Cartesian interface
    is commanded at a fraction of its 1 kHz servo rate."""
    image_size: int = 64
    """Width and height (pixels) of the mount camera's images (``ArmTask.render``)."""
    pose_hinge_grid: int = 0
    """The image observation's pose fit's global search over the target's hinges
    (``ArmTask.fit_target_pose``'s ``hinge_grid``; 0: the local restarts only)."""

    def __post_init__(self):
        super().__post_init__()
        if int(self.pose_hinge_grid) < 0:
            raise ValueError(f"pose_hinge_grid must be >= 0, got {self.pose_hinge_grid}")


class ArmTask(ArmPerception, Env):
    """A manipulation task: the arm of ``panda.xml`` with a task's tool, scene and camera mount.

    Subclasses set ``task_xml`` (the scene with its ``tool`` body, beside the task's module),
    ``controller`` (``CartesianController``: the action's meaning and the controlled point),
    ``mount`` (``CameraMount``), the target the camera looks for (``target_geoms``,
    ``target_joints``, ``target_hinge_period``: ``ArmPerception``'s) and the usual task hooks.
    ``qpos[:7]``/``qvel[:7]`` are the arm's.
    """

    task_xml: Path
    controller: CartesianController = CartesianController()
    mount: CameraMount = CameraMount()
    cameras = ("mount",)
    Config = ArmConfig

    @classmethod
    def mjcf(cls) -> str:
        return composed(str(cls.task_xml))

    @property
    def action_size(self) -> int:
        return self.controller.action_size

    @property
    def sys(self):
        """As ``Env.sys``. Setting it also changes this task in place by what the system says of
        the robot, and keeps what an earlier system set where this one says nothing: deprecated
        for that use -- ``with_system`` returns a new task built from the system alone. (Brax's
        domain randomisation sets it with traced systems: only their parameters apply.)"""
        return self._sys

    @sys.setter
    def sys(self, value) -> None:
        Env.sys.fset(self, value)
        self._apply_system(value, reset=False)

    def with_system(self, system) -> "ArmTask":
        """A copy of this task as ``system`` describes it; this task is untouched. Besides the
        parameters (``Env.with_system``): a ``"mount"`` camera in ``system.cameras`` (Real2Sim's
        fit of frames taken with the mount at its default pose) sets the mount's hand-eye offset
        (``CameraMount.with_hand_eye``), so every render and back-projection uses the identified
        camera; ``system.tool`` holds the tool at the identified grasp (``set_grasp``);
        ``system.controller`` calibrates the controller to the identified servos
        (``calibrate_controller``). What the system leaves out is the task's nominal one (the
        class's mount, the MJCF's grasp, the nominal controller), whatever this task had: e.g.
        ``task.with_system(system.replace(controller=None))`` is the task with the nominal
        controller."""
        out = super().with_system(system)
        out._apply_system(system, reset=True)
        return out

    def _apply_system(self, system, reset: bool) -> None:
        """Set the mount's hand-eye offset, the tool's grasp and the controller's calibration from
        ``system``; values it holds as tracers are not applied (inside a trace there is nothing to
        set). ``reset``: what the system leaves out goes back to the task's nominal."""
        def concrete(x) -> bool:
            return not isinstance(x, jax.core.Tracer)

        cam = (getattr(system, "cameras", None) or {}).get("mount")
        if cam is None:
            if reset:
                self.mount = type(self).mount
        elif concrete(cam.pos):
            self.mount = type(self).mount.with_hand_eye(cam)
        tool = getattr(system, "tool", None)
        if tool is None:
            if reset:
                self.clear_grasp()
        elif concrete(tool.pos_offset):
            self.set_grasp(tool.pos_offset, tool.rot_offset)
        calibration = getattr(system, "controller", None)
        if calibration is None:
            if reset and self.controller.joint_speed is not None:
                self.calibrate_controller(None)
        elif concrete(calibration.joint_speed):
            self.calibrate_controller(calibration.joint_speed)

    def servo_speed(self, params) -> np.ndarray:
        """How fast each of the arm's 7 servos moves its joint towards a target step, relative
        to the MJCF's: its gain over the joint's damping plus the servo's own (``kv``), in
        ``params`` (``PhysParams``, e.g. sysid's) over the nominal values'. The arm's controller
        sets targets a step from the *measured* joints, so in steady motion a joint covers that
        step times ``gain / damping`` per second: the quantity the exciting motions pin down
        (spatula twin 2: each joint's within 6 %, where gain and damping apart were 17-44 % off)."""
        def speed(p):
            gain = np.asarray(p.gain, np.float64)[:N_JOINTS]
            kv = -np.asarray(p.bias, np.float64)[:N_JOINTS, 2]
            return gain / (np.asarray(p.damping, np.float64)[:N_JOINTS] + kv)

        from twinrl.physics.params import PhysParams

        return speed(params) / speed(PhysParams.from_model(self.sim.mj_model))

    def calibrate_controller(self, joint_speed) -> None:
        """Calibrate the Cartesian controller to the servos' speeds (``servo_speed`` of the
        identified parameters; None: the nominal arm's): each joint's target step is divided by
        its speed (``CartesianController.joint_speed``), so the tool moves where it is commanded
        on an arm whose servos differ from the MJCF's. The real twin's controller takes the same
        calibration (``RealTwin.calibrate_controller``), as a robot's Cartesian interface is
        configured; ``System.controller`` carries it."""
        self.controller = dataclasses.replace(self.controller,
                                              joint_speed=check_joint_speed(joint_speed))

    grasp: tuple[np.ndarray, np.ndarray] | None = None
    """The tool's grasp in the hand as identified (``set_grasp``): ``(position offset (3,) in
    the hand's frame, rotation (3, 3) of the tool from its nominal orientation)``; None: the
    nominal grasp the MJCF writes."""

    def set_grasp(self, pos_offset, rot_offset) -> None:
        """Hold the tool ``pos_offset`` (m, the hand's frame) from where the MJCF puts it, turned
        by ``rot_offset`` (axis-angle, rad, in the tool's frame) -- ``Perturbation``'s
        ``tool_pos_offset`` / ``tool_rot_offset``, as ``visual.fit_body_offset`` identifies them
        from images (``System.tool``). The simulator's ``tool`` body moves (its
        contacts, its renders) and so does every tool point the task judges (``tool_pose``: the
        reward, success, the image observation's "tool"); the controller still servos the
        *nominal* tool centre point, as the robot's Cartesian interface does, and ``observe``
        (what the real twin reports: the state actor's and the residual's inputs) stays at the
        nominal kinematics. The image observation's pose estimate (``"estimate"``,
        ``estimate_from_obs``) is ``observe(..., nominal=False)``: the tool where the twin
        believes it is, at the identified grasp, as the image actor was taught to read it."""
        import mujoco

        from twinrl.render import rotvec_to_quat
        from twinrl.render.camera import quat_to_mat

        pos = np.asarray(pos_offset, np.float64).reshape(3)
        rot = np.asarray(rot_offset, np.float64).reshape(3)
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(rot))):
            raise ValueError(f"set_grasp: non-finite grasp offset {pos}, {rot}")
        held = self.__dict__.get("_grasp_offsets")
        if held is not None and np.array_equal(held[0], pos) and np.array_equal(held[1], rot):
            return  # held so already: the simulator is not rebuilt
        nominal = self.__dict__.setdefault("_nominal_sim", self.sim)
        model = copy.deepcopy(nominal.mj_model)
        tool = model.body("tool").id
        model.body_pos[tool] = nominal.mj_model.body_pos[tool] + pos
        turn = rotvec_to_quat(jnp.asarray(rot))
        q = np.zeros(4)
        mujoco.mju_mulQuat(q, nominal.mj_model.body_quat[tool].copy(),
                           np.asarray(turn, np.float64))
        model.body_quat[tool] = q
        # the constants compiled from the bodies' poses, as the real twin's Perturbation does
        # (the contact regulariser's invweight0 kept: MJX takes it from the nominal model)
        keep = {k: getattr(model, k).copy() for k in ("body_invweight0", "dof_invweight0")}
        mujoco.mj_setConst(model, mujoco.MjData(model))
        for k, v in keep.items():
            getattr(model, k)[:] = v
        self.sim = nominal.recompiled(model)
        self.grasp = (pos, np.asarray(quat_to_mat(turn), np.float64))
        self._grasp_offsets = (pos, rot)
        self.__dict__.pop("renderer", None)

    def clear_grasp(self) -> None:
        """Hold the tool where the MJCF puts it (undo ``set_grasp``)."""
        nominal = self.__dict__.pop("_nominal_sim", None)
        if nominal is not None:
            self.sim = nominal
            self.__dict__.pop("renderer", None)
        self.grasp = None
        self._grasp_offsets = None

    def set_posture(self, q_start) -> None:
        """Hold the controller's null space at ``q_start`` (the task's start posture)."""
        self.controller = dataclasses.replace(self.controller,
                                              posture=tuple(float(x) for x in q_start))

    def control(self, qpos, qvel, action):
        a = jnp.asarray(action, qpos.dtype).reshape(self.controller.action_size)
        target = self.controller(qpos[:N_JOINTS], a)
        # any actuators after the arm's 7 servos (none in the bundled tasks) hold 0
        return jnp.concatenate([target, jnp.zeros(self.sim.nu - N_JOINTS, target.dtype)])

    def tool_pose(self, qpos, nominal: bool = False) -> tuple[jax.Array, jax.Array]:
        """World ``(position, rotation)`` of the controller's tool centre point, carried by the
        tool at its identified grasp (``set_grasp``; the nominal kinematics' without one, or
        with ``nominal``: what a robot's own software reports, as the real twin's observation
        does)."""
        if self.grasp is None or nominal:
            return forward_kinematics(qpos[:N_JOINTS], self.controller.tcp)
        _, _, p, R = joint_frames(qpos[:N_JOINTS])
        dt = p.dtype
        pos, Rg = (jnp.asarray(x, dt) for x in self.grasp)
        mount = jnp.array([0.0, 0.0, TOOL_MOUNT], dt)
        return p + R @ (mount + pos + Rg @ jnp.asarray(self.controller.tcp, dt)), R @ Rg

    def tool_point(self, qpos, nominal: bool = False) -> jax.Array:
        """World position of the controller's tool centre point (``tool_pose``'s)."""
        return self.tool_pose(qpos, nominal)[0]

    # ------------------------------------------------------------------ initial guesses
    def approach_point(self, qpos) -> jax.Array | None:
        """Where a straight-line initial guess for trajectory optimisation takes the tool point
        before any contact (``approach_plan``); None: the task offers none."""
        return None

    def approach_plan(self, state, shortfall: float = 0.0) -> jax.Array:
        """(T, m) open-loop actions that command the tool point's displacement from where it
        starts to ``shortfall`` metres short of ``approach_point``, in a straight line at 90 % of
        the controller's speed limit (as many steps as that takes), then zeros (and zeros for
        every other action entry): an initial guess for trajectory optimisation that heads the
        tool for the object and leaves the manipulation to the optimiser. The commands are open
        loop and the servos lag them, so the tool covers only part of the way (spatula, reset key 3:
        5.8 of 13.5 cm; ``tests/envs/test_arm.py``); by itself it solves nothing. Needs a task
        with an ``approach_point``."""
        data = state.pipeline_state if hasattr(state, "pipeline_state") else state
        goal = self.approach_point(data.qpos)
        if goal is None:
            raise NotImplementedError(f"{type(self).__name__} has no approach_point")
        d = goal - self.tool_point(data.qpos)
        length = jnp.sqrt(jnp.sum(jnp.square(d)) + 1e-12)
        d = d * jnp.maximum(length - shortfall, 0.0) / length
        step = 0.9 * self.controller.max_step
        n = jnp.maximum(jnp.ceil(jnp.max(jnp.abs(d)) / step), 1.0)
        t = jnp.arange(self.episode_length)[:, None]
        move = jnp.where(t < n, d / (n * self.controller.max_step), 0.0)
        rest = jnp.zeros((self.episode_length, self.action_size - 3), move.dtype)
        return jnp.concatenate([move, rest], axis=1)

    # ------------------------------------------------------------------ checks
    def scripted_action(self, obs: np.ndarray) -> np.ndarray:
        """A hand-written expert (NumPy, from the privileged observation); each task has one."""
        raise NotImplementedError(f"{type(self).__name__} has no scripted expert")

    def gradcheck_action(self, obs: np.ndarray) -> np.ndarray:
        """The actions of ``gradcheck_scenario``: the scripted expert's, unless a task needs
        another to touch its object (the needle's expert threads the eye without touching it)."""
        return self.scripted_action(obs)

    def _first_tool_contact(self, qposes) -> int | None:
        """Index of the first of ``qposes`` at which a geom of the ``tool`` body penetrates
        another geom (MuJoCo C), or None."""
        import mujoco

        m = self.sim.mj_model
        d = mujoco.MjData(m)
        tool = m.body("tool").id
        for i, q in enumerate(qposes):
            d.qpos[:] = np.asarray(q, np.float64)
            mujoco.mj_forward(m, d)
            c = d.contact  # the d.ncon contacts
            if np.any((c.dist <= 0) & ((m.geom_bodyid[c.geom1] == tool)
                                       | (m.geom_bodyid[c.geom2] == tool))):
                return i
        return None

    def gradcheck_scenario(self, horizon: int = 30, seed: int = 0, lead: int = 5):
        """A ``twinrl.physics.scenes.Scenario`` of this task's scene through tool-object contact:
        the episode of ``gradcheck_action`` (the scripted expert) from ``reset(PRNGKey(seed))``, as
        the joint targets its controller sent (the actuators' ``ctrl``), in a window of ``horizon``
        control steps that starts ``lead`` steps before the first tool contact (a geom of the
        ``tool`` body touching another: an object resting on the table from the start does not
        count). The expert runs on past the episode's end where the window needs it, so the
        window holds ``horizon - lead`` steps from the first contact on even when that contact
        comes late. ``twinrl gradcheck TASK`` checks the physics' gradients on it; the
        controller's own derivative is checked with the task's return (``tests/envs``)."""
        from twinrl.physics.scenes import Scenario

        if not 1 <= int(horizon) <= self.episode_length:
            raise ValueError(f"horizon must be in [1, {self.episode_length}] (the episode's "
                             f"length), got {horizon}")
        step, control = jax.jit(self.step), jax.jit(self.control)
        s = jax.jit(self.reset)(jax.random.PRNGKey(seed))
        qs, vs, ctrls = [], [], []
        for _ in range(self.episode_length + int(horizon)):
            q, v = s.pipeline_state.qpos, s.pipeline_state.qvel
            a = jnp.asarray(self.gradcheck_action(np.asarray(s.obs)), q.dtype)
            qs.append(np.asarray(q))
            vs.append(np.asarray(v))
            ctrls.append(np.asarray(control(q, v, a)))
            s = step(s, a)
        ctrls = np.stack(ctrls)
        first = self._first_tool_contact(qs) or 0
        start = int(np.clip(first - lead, 0, self.episode_length))
        return Scenario(qpos=qs[start], qvel=vs[start], actions=ctrls[start:start + int(horizon)],
                        horizon=int(horizon))
