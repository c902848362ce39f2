"""``needle_threading``: pass the thread held by the arm through the eye of a needle whose place,
height and heading are random (SAM-RL, Lv et al. 2023, Sec. 5.3).

Scene ``needle_threading.xml``: a rigid thread (3 mm capsule, 12 cm) held level at the flange,
across the workspace (along world y); a needle standing with its eye (an 8 mm x 16 mm slot, 4 mm
thick) at x in [0.45, 0.6] m, y in [0, 0.1] m, height 0.15-0.25 m, its axis turned by up to
0.4 rad from the world y axis. The thread starts 10-16 cm short of the eye along y, up to 3 cm off
its axis, turned by up to 0.3 rad.
Control (``CartesianController``, yaw on): displacement of the thread's tip (3-D, at most 1.5 cm
per 0.04 s step) and a turn about the vertical (at most 0.1 rad per step); the thread is held level.

Observation (32, privileged): joint angles (7) and velocities (7), thread tip (3) and base (3), eye
centre (3), eye axis (3), the tip in the eye's frame (3), the thread's direction in the eye's frame
(3). Reward (per step, in [0, 1]): ``align * heading * (0.3 + 0.7 through) * small_control``;
``align`` a Gaussian bump of the tip's distance from the eye's axis line (0.1 at 6 cm),
``heading`` one of the sine of the angle between thread and axis (0.1 at 0.5), ``through`` one of
the tip's position along the axis relative to 3.5 cm past the eye (0.1 at 15 cm).
Success: the tip is at least ``THROUGH`` (2 cm) past the eye's plane and the thread crosses that
plane inside the slot.

What the camera must reveal: the eye's pose. The slot is open only along its axis: from the side
(azimuth near +-90 degrees about the needle) the head looks solid, and the thread and the arm hide
it from behind. The segmented target is the whole needle (eye and shank, ``target_geoms``); its
heading is ambiguous by a quarter turn where the head is seen edge-on and only the shank's 4 x 8
mm section tells it.

Real twin: grasp offset of the thread (position +-3 mm, tilt), friction, masses, joint damping and
servo gains, latency, observation noise, the camera's hand-eye offset.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.envs.arm.controller import CartesianController
from twinrl.envs.arm.kinematics import ik, solve_ik
from twinrl.envs.arm.mount import CameraMount
from twinrl.envs.arm.task import ARM_PERTURBATIONS, ArmConfig, ArmTask
from twinrl.envs.base import small_control, tolerance

__all__ = ["NeedleThreading", "NeedleThreadingConfig", "THROUGH"]

SLOT_HALF_WIDTH = 0.004
SLOT_HALF_HEIGHT = 0.008
THROUGH = 0.02
"""How far (m) past the eye's plane the thread's tip must be for success."""
THREAD_LENGTH = 0.12
TCP = (0.0, 0.0, THREAD_LENGTH)
SIDEWAYS = ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0))
"""Tool orientation with the thread (tool z) along world +y, level: the arm holds it across its
workspace (pointing the flange forward this low and close is at the Panda's joint limits)."""
NEEDLE_ORIGIN = np.array([0.52, 0.05, 0.2])
EYE_HEADING = np.pi / 2
"""The eye's axis at yaw 0 is world +y (the needle body's MJCF frame is turned by this)."""
"""The needle body's position in the MJCF: its slide joints are offsets from here."""


@dataclasses.dataclass(frozen=True)
class NeedleThreadingConfig(ArmConfig):
    episode_length: int = 50
    """Control steps per episode (2 s)."""
    image_size: int = 64
    """Width and height (pixels) of the mount camera's images. The eye shows on 8-33 of them,
    too few to fit its heading from a third of the random mount poses, and which view the
    camera takes decides the task: the camera Q chooses beats the default by +22 points on the
    real twins. At 128 (``twinrl run --set image_size=128``) the fit is wrong from 9-13 % of
    random views and the loop's image actor solves 74-86 % of 50 random-view starts where 64
    gave 50-75 %, but the default camera then solves 88-100 % of real starts and the choice has
    little left to win (twins 0 / 1: chosen 94 / 100 %, default 100 / 100 %). 64 keeps the task
    one where seeing is the problem."""
    eye_x: tuple[float, float] = (0.45, 0.6)
    """Range (m) of the eye centre's x at reset."""
    eye_y: tuple[float, float] = (0.0, 0.1)
    """Range (m) of the eye centre's y at reset."""
    eye_z: tuple[float, float] = (0.15, 0.25)
    """Range (m) of the eye centre's height at reset."""
    eye_yaw: tuple[float, float] = (-0.4, 0.4)
    """Range (rad) of the eye axis' heading from the world y axis."""
    start_back: tuple[float, float] = (0.10, 0.16)
    """Range (m) of how far short of the eye (along world y) the thread's tip starts."""
    start_offset: float = 0.03
    """Half-width (m) of the uniform start offset of the tip in y and z from the eye's."""
    start_yaw: float = 0.3
    """Half-width (rad) of the uniform start heading of the thread."""
    align_margin: float = 0.06
    """Distance (m) of the tip from the eye's axis line at which ``align`` has fallen to 0.1."""
    heading_margin: float = 0.5
    """Sine of the thread-axis angle at which ``heading`` has fallen to 0.1."""
    through_margin: float = 0.15
    """Distance (m) along the axis from 3.5 cm past the eye at which ``through`` is 0.1."""


class NeedleThreading(ArmTask):
    scene = "needle_threading"
    task_xml = Path(__file__).with_name("needle_threading.xml")
    controller = CartesianController(tcp=TCP, nominal=SIDEWAYS, yaw=True, max_step=0.015)
    mount = CameraMount(target=(0.52, 0.05, 0.2), azimuth=(-2.2, 2.2), elevation=(-0.3, 1.3),
                        distance=(0.3, 0.7), default=(0.0, 0.0, 0.0))
    target_geoms = ("eye_top", "eye_bottom", "eye_left", "eye_right", "shank")
    # the whole needle is the target the camera segments: the eye alone is 2-12 pixels of a 64 x
    # 64 image from the mount's poses, and its pose fit (``fit_target_pose``) was made on 70 %
    # of the views from random poses along demonstrations; with the 20 cm shank on 93 %, to a
    # median 0-2 mm (what the rest is off by, the eye's heading seen edge-on, a view fixes)
    target_joints = (7, 8, 9, 10)
    reward_term_names = ("align", "heading", "through", "small_control")
    perturbation_spec = ARM_PERTURBATIONS
    Config = NeedleThreadingConfig

    def __init__(self, config=None, params=None, name=None):
        super().__init__(config, params, name)
        mid = NEEDLE_ORIGIN - np.array([0.0, 0.13, 0.0])
        self._q_start = solve_ik(mid, tcp=TCP, nominal=SIDEWAYS)
        self.set_posture(self._q_start)

    # ------------------------------------------------------------------ geometry
    @staticmethod
    def eye(qpos) -> tuple[jax.Array, jax.Array]:
        """Eye centre (3,) and rotation (3, 3) (columns: axis, slot width, slot height)."""
        centre = jnp.asarray(NEEDLE_ORIGIN, qpos.dtype) + qpos[7:10]
        c, s = jnp.cos(EYE_HEADING + qpos[10]), jnp.sin(EYE_HEADING + qpos[10])
        z, o = jnp.zeros_like(c), jnp.ones_like(c)
        R = jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])
        return centre, R

    def thread(self, qpos, nominal: bool = False) -> tuple[jax.Array, jax.Array]:
        """The thread's tip and base (where it leaves the hand), world (at the identified grasp,
        ``ArmTask.tool_pose``; with ``nominal`` at the nominal one)."""
        tip, R = self.tool_pose(qpos, nominal)
        return tip, tip - THREAD_LENGTH * R[:, 2]

    def _in_eye_frame(self, qpos, tool=None):
        tip, base = (self.thread(qpos) if tool is None
                     else (tool[0], tool[0] - THREAD_LENGTH * tool[1][:, 2]))
        centre, R = self.eye(qpos)
        return R.T @ (tip - centre), R.T @ (base - centre)

    def initial_state(self, rng):
        c = self.config
        k = jax.random.split(rng, 8)
        u = lambda key, lo_hi: jax.random.uniform(key, (), minval=lo_hi[0], maxval=lo_hi[1])
        eye = jnp.stack([u(k[0], c.eye_x), u(k[1], c.eye_y), u(k[2], c.eye_z)])
        eye_yaw = u(k[3], c.eye_yaw)
        off = jax.random.uniform(k[4], (2,), minval=-c.start_offset, maxval=c.start_offset)
        tip = eye + jnp.stack([off[0], -u(k[5], c.start_back), off[1]])
        yaw = jax.random.uniform(k[6], (), minval=-c.start_yaw, maxval=c.start_yaw)
        q = ik(tip, self._q_start, TCP, SIDEWAYS, yaw, iters=40)
        qpos = jnp.concatenate([q, eye - jnp.asarray(NEEDLE_ORIGIN, eye.dtype), eye_yaw[None]])
        return qpos, jnp.zeros(self.sim.nv)

    def observe(self, qpos, qvel, nominal: bool = True):
        # the robot reports its thread by its nominal kinematics, as the real twin does; a pose
        # estimate (``nominal=False``) puts it at the identified grasp (``ArmTask.set_grasp``)
        tip, base = self.thread(qpos, nominal=nominal)
        centre, R = self.eye(qpos)
        tip_e = R.T @ (tip - centre)
        dir_e = R.T @ (tip - base) / THREAD_LENGTH
        return jnp.concatenate([qpos[:7], qvel[:7], tip, base, centre, R[:, 0], tip_e,
                                dir_e]).astype(jnp.float32)

    def state_from_obs(self, obs):
        """``(qpos, qvel)`` of an observation: the joints, the eye's offset from its origin and
        its yaw (from its axis); the eye does not move (velocity zero)."""
        obs = jnp.asarray(obs)
        yaw = jnp.arctan2(obs[..., 24], obs[..., 23]) - EYE_HEADING
        yaw = jnp.arctan2(jnp.sin(yaw), jnp.cos(yaw))
        qpos = jnp.concatenate([obs[..., :7],
                                obs[..., 20:23] - jnp.asarray(NEEDLE_ORIGIN, obs.dtype),
                                yaw[..., None]], axis=-1)
        zero = jnp.zeros(obs.shape[:-1] + (4,), obs.dtype)
        return qpos, jnp.concatenate([obs[..., 7:14], zero], axis=-1)

    def reward_terms(self, qpos, qvel, action):
        c = self.config
        tip_e, base_e = self._in_eye_frame(qpos)
        direction = (tip_e - base_e) / THREAD_LENGTH
        return {
            "align": tolerance(tip_e[1:], c.align_margin, 0.1, axis=-1),
            "heading": tolerance(direction[1:], c.heading_margin, 0.1, axis=-1),
            "through": tolerance(tip_e[0] - (THROUGH + 0.015), c.through_margin, 0.1),
            "small_control": small_control(action),
        }

    def combine(self, terms):
        return (terms["align"] * terms["heading"] * (0.3 + 0.7 * terms["through"])
                * terms["small_control"])

    def scripted_action(self, obs: np.ndarray) -> np.ndarray:
        """A hand-written expert from the privileged observation: turn the thread onto the eye's
        axis, bring its tip onto the axis 5 cm short of the eye, then push it through. For tests
        and gradient-check scenarios; the demonstrations are trajectory optimisation's."""
        o = np.asarray(obs, np.float64)
        axis, tip_e, dir_e = o[23:26], o[26:29], o[29:32]
        side = np.array([-axis[1], axis[0], 0.0])
        off_axis = tip_e[1] * side + np.array([0.0, 0.0, tip_e[2]])
        aligned = (np.hypot(tip_e[1], tip_e[2]) < 0.0025 and abs(dir_e[1]) < 0.03) or (
            tip_e[0] > -0.005)  # once in the eye, keep going
        along = (0.06 - tip_e[0]) if aligned else np.clip(-0.05 - tip_e[0], -0.02, 0.02)
        a = np.zeros(4)
        # half the error per step: the servos lag a step, a full correction overshoots
        move = (-0.5 * off_axis + along * axis) / self.controller.max_step
        a[:3] = move / max(1.0, np.abs(move).max())  # scaled, not clipped: keep its direction
        a[3] = -0.5 * dir_e[1] / self.controller.max_yaw
        return np.clip(a, -1.0, 1.0).astype(np.float32)

    def gradcheck_action(self, obs: np.ndarray) -> np.ndarray:
        """The expert aiming 5 mm beside the eye's axis (the thread clears the slot by 2.5 mm),
        so the thread rubs the slot's side on its way through: a gradient check through contact."""
        o = np.array(obs, np.float64)
        o[27] -= 0.005
        return self.scripted_action(o)

    def success(self, qpos, qvel, tool=None) -> jax.Array:
        """1.0 when the tip is ``THROUGH`` past the eye's plane and the thread crosses the plane
        inside the slot, else 0.0. ``tool``: the true tip's ``(position, rotation)`` (default:
        ``tool_pose``'s, at the identified grasp)."""
        tip_e, base_e = self._in_eye_frame(qpos, tool)
        span = tip_e[0] - base_e[0]
        lam = jnp.clip(-base_e[0] / jnp.where(span > 0, span, 1.0), 0.0, 1.0)
        cross = base_e + lam * (tip_e - base_e)
        inside = (jnp.abs(cross[1]) < SLOT_HALF_WIDTH) & (jnp.abs(cross[2]) < SLOT_HALF_HEIGHT)
        return ((tip_e[0] > THROUGH) & (base_e[0] < 0) & inside).astype(jnp.float32)
