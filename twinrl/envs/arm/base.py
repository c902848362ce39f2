"""The robot of the manipulation tasks: a Panda-kinematics arm, its Cartesian controller, the tool
at its flange and the camera mount (SAM-RL, Lv et al. 2023, Sec. 4: a Franka Panda does the task
while a second arm moves an RGB-D camera).

- ``panda.xml`` beside this file is the arm (7 revolute joints, position servos, gravity
  compensated); ``compose(task_xml)`` puts it into a task's scene and attaches the task's ``tool``
  body (peg, spatula, thread) at the flange. The result is one plain MJCF string, the same for MJX
  and for the real twin's MuJoCo C engine.
- ``forward_kinematics`` and ``jacobian`` are the arm's kinematics from Franka's published modified
  Denavit-Hartenberg table (``DH``), in JAX: the controller runs them on measured joint angles
  (as a robot's controller uses its nominal kinematic model), identically in the simulator and on
  the real twin, and ``jax.grad`` goes through them.
- ``CartesianController``: an end-effector command (a displacement of the tool centre point, plus
  a rotation about the vertical where the task needs it) becomes joint targets by damped least
  squares on that Jacobian, with the tool axis pulled towards the task's nominal direction and a
  null-space pull towards the home posture. Differentiable end to end, so the gradient of a return
  w.r.t. end-effector actions goes through the controller, the servos, the arm and the contacts.
- ``CameraMount``: a camera carried by a second arm, modelled by what matters for sensing: a
  reachable workspace (a spherical shell patch around a look-at point: azimuth, elevation,
  distance ranges), a look-at constraint, and a speed limit (``steps_to_move``). Its pose is a
  controllable input: ``pose(coords)`` gives a ``twinrl.render.Camera`` that is differentiable in
  the coordinates, which is what the sensing-aware camera choice optimises.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import xml.etree.ElementTree as ET
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["ARM_XML", "DH", "FLANGE", "HOME", "JOINT_RANGE", "compose", "forward_kinematics",
           "joint_frames", "jacobian", "kinematics_and_jacobian",
           "heading", "orientation_error", "CartesianController",
           "CameraMount", "ik", "solve_ik", "ArmTask", "ArmConfig", "DOWN"]

ARM_XML = Path(__file__).with_name("panda.xml")

# Franka's modified DH parameters, one row per joint: (a_{i-1}, d_i, alpha_{i-1}); the flange
# sits d = 0.107 along joint 7's axis. panda.xml's body offsets are these rows (tested).
DH = np.array([
    [0.0, 0.333, 0.0],
    [0.0, 0.0, -np.pi / 2],
    [0.0, 0.316, np.pi / 2],
    [0.0825, 0.0, np.pi / 2],
    [-0.0825, 0.384, -np.pi / 2],
    [0.0, 0.0, np.pi / 2],
    [0.088, 0.0, np.pi / 2],
])
FLANGE = 0.107
TOOL_MOUNT = 0.05
"""Distance (m) from the flange to the tool's frame along the flange axis (the hand's thickness)."""
HOME = np.array([0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4])
"""The Panda's 'ready' posture (flange at (0.307, 0, 0.590), pointing down)."""
JOINT_RANGE = np.array([
    [-2.8973, 2.8973], [-1.7628, 1.7628], [-2.8973, 2.8973], [-3.0718, -0.0698],
    [-2.8973, 2.8973], [-0.0175, 3.7525], [-2.8973, 2.8973]])
N_JOINTS = 7


# ---------------------------------------------------------------------- MJCF composition
def compose(task_xml: str | Path, base_pos=(0.0, 0.0, 0.0)) -> str:
    """The MJCF of a task: its scene file with the arm (``panda.xml``) at ``base_pos`` and the
    scene's top-level ``<body name="tool">`` moved onto the arm's ``tool_mount`` site frame.

    The scene file is itself a valid MJCF (the tool then floats where it is written), so a user can
    open it alone; its ``<option>``, ``<visual>`` and assets win over the arm's."""
    scene = ET.parse(task_xml).getroot()
    arm = ET.parse(ARM_XML).getroot()
    world = scene.find("worldbody")
    tool = world.find("body[@name='tool']")
    if tool is None:
        raise ValueError(f"{task_xml}: the scene needs a top-level <body name='tool'> to attach "
                         "at the arm's flange")
    world.remove(tool)
    hand = arm.find(".//body[@name='hand']")
    tool.set("pos", f"0 0 {TOOL_MOUNT}")
    tool.set("gravcomp", "1")  # the controller compensates its configured payload, as Franka's does
    tool.attrib.pop("quat", None)
    hand.append(tool)
    link0 = arm.find("worldbody/body[@name='link0']")
    link0.set("pos", " ".join(f"{v:g}" for v in base_pos))
    world.insert(0, link0)
    for tag in ("compiler", "default", "actuator"):
        part = arm.find(tag)
        if part is None:
            continue
        mine = scene.find(tag)
        if mine is None:
            scene.insert(0, part)
        else:
            mine.extend(list(part))
    return ET.tostring(scene, encoding="unicode")


# ---------------------------------------------------------------------- kinematics
def _dh_constants() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The modified-DH transforms RotX(alpha) TransX(a) RotZ(theta) TransZ(d) of the 7 joints as
    ``R = cos(theta) C + sin(theta) S + K`` and a constant ``p`` (``a``, ``d``, ``alpha`` are
    fixed): ``(C, S, K (7, 3, 3), p (7, 3))``."""
    a, d, alpha = DH[:N_JOINTS].T
    ca, sa = np.cos(alpha), np.sin(alpha)
    C, S, K = (np.zeros((N_JOINTS, 3, 3)) for _ in range(3))
    C[:, 0, 0], C[:, 1, 1], C[:, 2, 1] = 1.0, ca, sa
    S[:, 0, 1], S[:, 1, 0], S[:, 2, 0] = -1.0, ca, sa
    K[:, 1, 2], K[:, 2, 2] = -sa, ca
    return C, S, K, np.stack([a, -sa * d, ca * d], axis=1)


_DH_C, _DH_S, _DH_K, _DH_P = _dh_constants()


def joint_frames(q: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """World frames of the 7 joints and the flange for joint angles ``q`` (7,) (base at origin):
    ``(joint positions (7, 3), joint axes (7, 3), flange position (3,), flange rotation
    (3, 3))``.

    Every joint's transform is computed at once (``_dh_constants``) and only the chain's
    products are sequential: an arm step calls this four times, and a per-joint ``jnp.array``
    of traced scalars was 1,155 of its 6,887 jaxpr equations."""
    dt = q.dtype
    ct, st = jnp.cos(q)[:, None, None], jnp.sin(q)[:, None, None]
    Rs = ct * jnp.asarray(_DH_C, dt) + st * jnp.asarray(_DH_S, dt) + jnp.asarray(_DH_K, dt)
    R = jnp.eye(3, dtype=dt)
    p = jnp.zeros(3, dt)
    pos, axes = [], []
    for i in range(N_JOINTS):
        p = p + R @ jnp.asarray(_DH_P[i], dt)
        R = R @ Rs[i]
        pos.append(p)
        axes.append(R[:, 2])
    p = p + R[:, 2] * FLANGE
    return jnp.stack(pos), jnp.stack(axes), p, R


def _tool_point(p, R, tcp):
    tcp = jnp.asarray(tcp, p.dtype) + jnp.array([0.0, 0.0, TOOL_MOUNT], p.dtype)
    return p + R @ tcp


def forward_kinematics(q: jax.Array, tcp=(0.0, 0.0, 0.0), base=(0.0, 0.0, 0.0)):
    """``(position (3,), rotation (3, 3))`` of the tool centre point: ``tcp`` in the tool frame
    (which is the flange frame moved ``TOOL_MOUNT`` along its axis)."""
    _, _, p, R = joint_frames(q)
    return _tool_point(p, R, tcp) + jnp.asarray(base, q.dtype), R


def kinematics_and_jacobian(q: jax.Array, tcp=(0.0, 0.0, 0.0)):
    """``forward_kinematics(q, tcp)`` and ``jacobian(q, tcp)`` from one pass over the chain:
    ``(position (3,), rotation (3, 3), Jacobian (6, 7))``."""
    pos, axes, p, R = joint_frames(q)
    tip = _tool_point(p, R, tcp)
    jp = jnp.cross(axes, tip[None, :] - pos)
    return tip, R, jnp.concatenate([jp.T, axes.T], axis=0)


def jacobian(q: jax.Array, tcp=(0.0, 0.0, 0.0)) -> jax.Array:
    """Geometric Jacobian (6, 7) of the tool centre point: rows 0-2 linear, 3-5 angular (world)."""
    return kinematics_and_jacobian(q, tcp)[2]


def _rot_z(angle):
    c, s = jnp.cos(angle), jnp.sin(angle)
    z, o = jnp.zeros_like(angle), jnp.ones_like(angle)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


DOWN = ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))
"""Tool orientation with its z axis pointing down (the flange's in the 'ready' posture)."""


def heading(R: jax.Array, nominal) -> jax.Array:
    """Rotation about the vertical (rad) of tool orientation ``R`` relative to ``nominal``."""
    rel = R @ jnp.asarray(nominal, R.dtype).T
    return jnp.arctan2(rel[1, 0] - rel[0, 1], rel[0, 0] + rel[1, 1])


def orientation_error(R: jax.Array, R_des: jax.Array) -> jax.Array:
    """Small-angle rotation vector (world) taking ``R`` towards ``R_des``."""
    return 0.5 * jnp.sum(jnp.cross(R.T, R_des.T), axis=0)


@dataclasses.dataclass(frozen=True)
class CartesianController:
    """End-effector command -> joint position targets (damped least squares).

    Action layout: ``[dx, dy, dz]`` in [-1, 1] (times ``max_step`` metres per control step), and,
    with ``yaw=True``, a fourth entry: rotation about the vertical (times ``max_yaw`` rad per step).
    The tool's orientation is pulled towards ``nominal`` turned about the vertical by its current
    heading (plus the commanded turn) with gain ``tilt_gain`` each step, so the tool stays level
    without the policy spending actions on it.
    """

    tcp: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The controlled point in the tool frame (the peg's tip, the blade's edge, the thread's
    end)."""
    nominal: tuple = DOWN
    """The tool's nominal orientation (rows of a world rotation matrix) at heading 0."""
    yaw: bool = False
    """Whether the action has a fourth entry turning the tool about the vertical."""
    max_step: float = 0.02
    """Metres per control step at |action| = 1."""
    max_yaw: float = 0.1
    """Radians per control step at |action| = 1."""
    tilt_gain: float = 0.5
    """Fraction of the tool's orientation error corrected per step."""
    damping: float = 0.05
    """Damped-least-squares damping (lambda, in the 6-D task space's units)."""
    posture_gain: float = 0.1
    """Null-space pull towards ``posture`` per step (fraction of the joint error)."""
    posture: tuple = tuple(HOME)
    """The joint posture the null space is pulled towards (the task's start posture)."""
    joint_speed: tuple | None = None
    """Per joint, how fast its servo closes a step of its target relative to the nominal arm's
    (gain over damping, over the MJCF's: ``ArmTask.servo_speed``), as identified; each joint's step
    is divided by it, so the tool moves as commanded whatever the servos (None: the nominal
    arm's, all ones). The targets are set from the measured joints, so a servo 30 % faster
    than nominal moves its joint 30 % further per step and bends the commanded direction
    (``bench/arm_controller.py``)."""

    @property
    def action_size(self) -> int:
        return 4 if self.yaw else 3

    def __call__(self, q: jax.Array, action: jax.Array) -> jax.Array:
        """Joint targets (7,) for measured joint angles ``q`` (7,) and ``action`` (clipped)."""
        a = jnp.clip(action, -1.0, 1.0)
        _, R, J = kinematics_and_jacobian(q, self.tcp)
        turn = a[3] * self.max_yaw if self.yaw else jnp.zeros((), q.dtype)
        R_des = _rot_z(heading(R, self.nominal) + turn) @ jnp.asarray(self.nominal, q.dtype)
        dx = jnp.concatenate([self.max_step * a[:3],
                              self.tilt_gain * orientation_error(R, R_des)])
        if self.yaw:  # the commanded turn itself, not a fraction of it
            dx = dx.at[5].add((1.0 - self.tilt_gain) * turn)
        JJt = J @ J.T + self.damping ** 2 * jnp.eye(6, dtype=q.dtype)
        pinv = J.T @ jnp.linalg.solve(JJt, jnp.eye(6, dtype=q.dtype))
        posture = jnp.asarray(self.posture, q.dtype)
        dq = pinv @ dx + _null_space(J) @ (self.posture_gain * (posture - q))
        if self.joint_speed is not None:
            dq = dq / jnp.asarray(self.joint_speed, q.dtype)
        lo, hi = (jnp.asarray(JOINT_RANGE[:, i], q.dtype) for i in (0, 1))
        return jnp.clip(q + dq, lo, hi)


def check_joint_speed(joint_speed) -> tuple[float, ...] | None:
    """``joint_speed`` (``CartesianController.joint_speed``) as 7 positive finite floats, or
    None; anything else raises one line naming it."""
    if joint_speed is None:
        return None
    js = np.asarray(joint_speed, np.float64).reshape(-1)
    if js.shape != (N_JOINTS,) or not np.all(np.isfinite(js)) or np.any(js <= 0):
        raise ValueError(f"joint_speed must be {N_JOINTS} positive finite numbers (each servo's "
                         f"speed relative to the nominal arm's), got {np.asarray(joint_speed)!r}")
    return tuple(float(x) for x in js)


def _null_space(J: jax.Array) -> jax.Array:
    """Projector onto the null space of ``J`` (6, 7): a posture motion through it leaves the
    tool where it is (the damped pseudo-inverse's projector would leak into the task space)."""
    eye = jnp.eye(J.shape[1], dtype=J.dtype)
    return eye - J.T @ jnp.linalg.solve(J @ J.T + 1e-8 * jnp.eye(6, dtype=J.dtype), J)


@functools.lru_cache(maxsize=None)
def _ik_fn(tcp, nominal, iters):
    def solve(target, yaw, q0):
        q = ik(target, q0, tcp, nominal, yaw, iters)
        p, R = forward_kinematics(q, tcp)
        R_des = _rot_z(yaw) @ jnp.asarray(nominal, q.dtype)
        err = jnp.sum(jnp.square(p - target)) + jnp.sum(jnp.square(orientation_error(R, R_des)))
        lo, hi = (jnp.asarray(JOINT_RANGE[:, i], q.dtype) for i in (0, 1))
        return q, err, jnp.min(jnp.minimum(q - lo, hi - q) / (hi - lo))
    return jax.jit(jax.vmap(solve, in_axes=(None, None, 0)))


def solve_ik(target, tcp=(0.0, 0.0, 0.0), nominal=DOWN, yaw: float = 0.0, restarts: int = 64,
             iters: int = 100, seed: int = 0) -> np.ndarray:
    """Joint angles (NumPy) that put the tool centre point at ``target`` with the tool at
    ``nominal`` orientation turned by ``yaw`` about the vertical (for a task's start posture).

    Damped Gauss-Newton from ``HOME`` and ``restarts - 1`` random postures; of the solutions that
    reach the pose (to 1e-3), the one whose closest joint limit is farthest (as a fraction of
    that joint's range)."""
    rng = np.random.default_rng(seed)
    q0 = np.concatenate([HOME[None], rng.uniform(JOINT_RANGE[:, 0], JOINT_RANGE[:, 1],
                                                 size=(restarts - 1, N_JOINTS))])
    f = _ik_fn(tuple(tcp), tuple(map(tuple, nominal)), int(iters))
    dtype = jnp.result_type(float)
    q, err, margin = (np.asarray(x, np.float64) for x in f(
        jnp.asarray(target, dtype), jnp.asarray(yaw, dtype), jnp.asarray(q0, dtype)))
    ok = err < 1e-6
    if not ok.any():
        raise ValueError(f"no joint posture of the arm reaches {np.round(target, 3).tolist()} at "
                         f"that orientation (best squared error {err.min():.2g})")
    return q[np.flatnonzero(ok)[np.argmax(margin[ok])]]


def ik(target: jax.Array, q_init: jax.Array, tcp=(0.0, 0.0, 0.0), nominal=DOWN, yaw=0.0,
       iters: int = 30, posture=None) -> jax.Array:
    """Joint angles putting the tool centre point at ``target`` with the tool at ``nominal``
    turned by ``yaw``, by ``iters`` damped Gauss-Newton steps from ``q_init`` (JAX; jit/vmap-able,
    for resets), with a null-space pull to ``posture`` (default ``q_init``)."""
    target = jnp.asarray(target)
    q_init = jnp.asarray(q_init, target.dtype)  # float32, or float64 under x64
    dtype = q_init.dtype
    R_des = _rot_z(jnp.asarray(yaw, dtype)) @ jnp.asarray(nominal, dtype)
    rest = q_init if posture is None else jnp.asarray(posture, dtype)
    lo, hi = (jnp.asarray(JOINT_RANGE[:, i], dtype) for i in (0, 1))

    def body(_, q):
        p, R, J = kinematics_and_jacobian(q, tcp)
        err = jnp.concatenate([target - p, orientation_error(R, R_des)])
        pinv = J.T @ jnp.linalg.solve(J @ J.T + 1e-4 * jnp.eye(6, dtype=dtype),
                                      jnp.eye(6, dtype=dtype))
        dq = pinv @ err + _null_space(J) @ (0.1 * (rest - q))
        return jnp.clip(q + dq, lo, hi)

    return jax.lax.fori_loop(0, iters, body, q_init)


# ---------------------------------------------------------------------- the camera mount
@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class CameraMount:
    """A camera carried by a second arm around a look-at point: its reachable poses are
    ``target + distance * (cos el cos az, cos el sin az, sin el)`` looking at ``target``, with
    azimuth, elevation and distance in their ranges.

    ``pose(coords)`` takes *unconstrained* coordinates (3,) mapped into the ranges by a sigmoid,
    so gradient ascent (sensing: the camera pose that maximises Q) cannot leave the workspace;
    ``coords = 0`` is the middle of every range. ``box_coords``/``coords_of`` convert from and to
    ``(azimuth rad, elevation rad, distance m)``.
    """

    target: tuple[float, float, float] = (0.5, 0.0, 0.05)
    """The look-at point (world, m)."""
    azimuth: tuple[float, float] = (-2.0, 2.0)
    """Range (rad) of the camera's direction about the vertical, from the target's +x side."""
    elevation: tuple[float, float] = (0.25, 1.35)
    """Range (rad) of the camera's height angle above the target."""
    distance: tuple[float, float] = (0.45, 0.8)
    """Range (m) of the camera's distance from the target."""
    default: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The default (fixed-camera baseline) pose's unconstrained coordinates."""
    fovy: float = 50.0
    """Vertical field of view (degrees)."""
    max_speed: float = 0.25
    """Largest move (rad of azimuth/elevation, or m of distance) the mount makes per control step:
    moving the camera costs ``steps_to_move`` time steps."""
    pos_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The camera's offset (m) from the commanded pose, in the commanded camera frame: the
    hand-eye calibration (``with_hand_eye``), zero in the nominal model. A real mount's camera
    sits where its hand-eye offset puts it (``RealTwin.move_camera``)."""
    rot_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The camera's rotation (rotation vector, rad) from the commanded orientation, in the
    commanded camera frame: the other half of the hand-eye calibration."""

    def _ranges(self):
        return np.array([self.azimuth, self.elevation, self.distance], np.float64)

    def spherical(self, coords: jax.Array) -> jax.Array:
        """``(azimuth, elevation, distance)`` of unconstrained ``coords``."""
        r = jnp.asarray(self._ranges(), coords.dtype)
        return r[:, 0] + (r[:, 1] - r[:, 0]) * jax.nn.sigmoid(coords)

    def coords_of(self, spherical) -> np.ndarray:
        """Unconstrained coordinates of ``(azimuth, elevation, distance)`` (inside the ranges)."""
        r = self._ranges()
        u = (np.asarray(spherical, np.float64) - r[:, 0]) / (r[:, 1] - r[:, 0])
        if np.any(u <= 0) or np.any(u >= 1):
            raise ValueError(f"camera pose {spherical} is outside the mount's workspace "
                             f"azimuth {self.azimuth}, elevation {self.elevation}, "
                             f"distance {self.distance}")
        return np.log(u) - np.log1p(-u)

    def eye(self, coords: jax.Array) -> jax.Array:
        az, el, dist = self.spherical(coords)
        d = jnp.stack([jnp.cos(el) * jnp.cos(az), jnp.cos(el) * jnp.sin(az), jnp.sin(el)])
        return jnp.asarray(self.target, coords.dtype) + dist * d

    def quat(self, coords: jax.Array) -> jax.Array:
        """Camera orientation quaternion (w, x, y, z), MuJoCo's convention (looking down its -z,
        image up its +y): turned by the azimuth about the vertical and tilted down by the
        elevation, from the pose that looks along -x with the world's z up."""
        from twinrl.render import quat_mul

        az, el, _ = self.spherical(coords)
        q_az = jnp.stack([jnp.cos(az / 2), 0.0 * az, 0.0 * az, jnp.sin(az / 2)])
        q_el = jnp.stack([jnp.cos(-el / 2), 0.0 * el, jnp.sin(-el / 2), 0.0 * el])
        q0 = jnp.full(4, 0.5, coords.dtype)  # columns (y, z, x): right, up, backwards
        return quat_mul(quat_mul(q_az, q_el), q0)

    def xmat(self, coords: jax.Array) -> jax.Array:
        """Camera orientation (columns: image right, image up, backwards)."""
        from twinrl.render import quat_to_mat

        return quat_to_mat(self.quat(coords))

    def camera(self, coords: jax.Array, width: int = 64, height: int = 64):
        """The ``twinrl.render.Camera`` at ``coords`` (differentiable in them), the hand-eye
        offset (``pos_offset``, ``rot_offset``) included."""
        from twinrl.render import Camera, quat_mul, rotvec_to_quat

        coords = jnp.asarray(coords)
        eye, quat = self.eye(coords), self.quat(coords)
        if any(self.pos_offset) or any(self.rot_offset):
            dt = coords.dtype
            eye = eye + self.xmat(coords) @ jnp.asarray(self.pos_offset, dt)
            quat = quat_mul(quat, rotvec_to_quat(jnp.asarray(self.rot_offset, dt)))
        return Camera(eye, quat, jnp.asarray(self.fovy, coords.dtype), int(width), int(height))

    def with_hand_eye(self, camera, coords=None) -> "CameraMount":
        """This mount with the hand-eye offset that puts its camera at ``camera`` (a
        ``twinrl.render.Camera``, e.g. Real2Sim's fit of frames taken with the mount commanded to
        ``coords``, default ``default``): the offset of ``camera`` from the commanded pose, in the
        commanded camera frame."""
        from twinrl.render import quat_to_mat

        c = jnp.asarray(self.default if coords is None else coords, jnp.float32)
        R0 = np.asarray(self.xmat(c), np.float64)
        eye0 = np.asarray(self.eye(c), np.float64)
        R = np.asarray(quat_to_mat(jnp.asarray(camera.quat, jnp.float32)), np.float64)
        dR = R0.T @ R
        import mujoco

        q = np.empty(4)
        mujoco.mju_mat2Quat(q, dR.reshape(-1))
        rv = np.empty(3)
        mujoco.mju_quat2Vel(rv, q, 1.0)
        dp = R0.T @ (np.asarray(camera.pos, np.float64) - eye0)
        return dataclasses.replace(self, pos_offset=tuple(float(x) for x in dp),
                                   rot_offset=tuple(float(x) for x in rv))

    def calibration_poses(self, n: int) -> np.ndarray:
        """``n`` mount poses (unconstrained coordinates, ``(n, 3)``) to calibrate the hand-eye
        offset from: the default pose first, then poses spread over the middle 70 % of each
        range (a Halton sequence: deterministic, every prefix well spread). Several are needed:
        from one pose a sideways shift of the camera and a turn of it give nearly the same
        image."""
        if int(n) < 1:
            raise ValueError(f"calibration_poses: n must be >= 1, got {n}")
        out = [np.asarray(self.default, np.float64)]
        for k in range(1, int(n)):
            u = np.array([_radical_inverse(k, b) for b in (2, 3, 5)])
            out.append(self.coords_of(self._ranges()[:, 0] + (0.15 + 0.7 * u)
                                      * np.diff(self._ranges(), axis=1)[:, 0]))
        return np.stack(out)

    def steps_to_move(self, coords_from, coords_to) -> int:
        """Control steps the mount needs between two poses at its speed limit."""
        a = np.asarray(self.spherical(jnp.asarray(coords_from, jnp.float32)))
        b = np.asarray(self.spherical(jnp.asarray(coords_to, jnp.float32)))
        return int(np.ceil(np.max(np.abs(b - a)) / self.max_speed))


def target_cloud(camera, depth: jax.Array, mask: jax.Array) -> jax.Array:
    """What the depth image says of the target, in the world frame: the mean (3,) and spread
    (3,) of its pixels' back-projected points, seen from ``camera`` (the pose the robot
    commanded), and ``log(1 + its pixel count)`` -- 7 numbers, 0 where it is not seen. Soft and
    differentiable in the pose with a soft ``mask``."""
    from twinrl.render.pointcloud import depth_to_points

    pts, w = depth_to_points(camera, depth, mask)
    n = jnp.sum(w)
    safe = jnp.maximum(n, 1e-3)
    mean = jnp.sum(w[:, None] * pts, axis=0) / safe
    spread = jnp.sqrt(jnp.sum(w[:, None] * jnp.square(pts - mean), axis=0) / safe + 1e-10)
    return jnp.concatenate([mean, spread, jnp.log1p(n)[None]]).astype(jnp.float32)


@functools.lru_cache(maxsize=None)
def composed(task_xml: str) -> str:
    """``compose(task_xml)``, cached: every task instance shares one string."""
    return compose(task_xml)



# ---------------------------------------------------------------------- the arm tasks' Env
from twinrl._jaxconfig import exact_matmuls  # noqa: E402
from twinrl.envs.base import Env, PerturbationSpec, TaskConfig  # noqa: E402

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


class ArmTask(Env):
    """A manipulation task: the arm of ``panda.xml`` with a task's tool, scene and camera mount.

    Subclasses set ``task_xml`` (the scene with its ``tool`` body, beside the task's module),
    ``controller`` (``CartesianController``: the action's meaning and the controlled point),
    ``mount`` (``CameraMount``) and the usual task hooks. ``qpos[:7]``/``qvel[:7]`` are the arm's.
    """

    task_xml: Path
    controller: CartesianController = CartesianController()
    mount: CameraMount = CameraMount()
    cameras = ("mount",)
    target_geoms: tuple[str, ...] = ()
    """Geoms whose pose the camera must reveal (the hole's fixture, the pancake, the needle's eye):
    what ``bench/manipulation.py`` counts to say from how much of the mount's workspace the target
    is visible."""
    target_joints: tuple[int, ...] = ()
    """``qpos`` indices of the joints that place the target (``fit_target_pose`` estimates them
    from an image); () where its pose is not estimated."""
    target_hinge_period: float = np.pi
    """The turn about a target hinge after which the target looks the same (the needle's eye, a
    rectangular ring: half a turn); ``fit_target_pose`` reports hinge angles modulo it."""
    Config = ArmConfig

    @classmethod
    def mjcf(cls) -> str:
        return composed(str(cls.task_xml))

    @property
    def action_size(self) -> int:
        return self.controller.action_size

    @property
    def sys(self):
        """As ``Env.sys``; a ``System`` with a ``"mount"`` camera (Real2Sim's fit of frames taken
        with the mount at its default pose) also sets the mount's hand-eye offset
        (``CameraMount.with_hand_eye``), so every render and back-projection of this task uses the
        identified camera."""
        return self._sys

    @sys.setter
    def sys(self, value) -> None:
        Env.sys.fset(self, value)
        cam = (getattr(value, "cameras", None) or {}).get("mount")
        if cam is not None and not isinstance(cam.pos, jax.core.Tracer):
            self.mount = type(self).mount.with_hand_eye(cam)
        objects = getattr(value, "objects", None) or {}
        tool = objects.get("tool")
        if tool is not None and not isinstance(tool["pos_offset"], jax.core.Tracer):
            self.set_grasp(tool["pos_offset"], tool["rot_offset"])
        speed = (objects.get("controller") or {}).get("joint_speed")
        if speed is not None and not isinstance(speed, jax.core.Tracer):
            self.calibrate_controller(speed)

    def servo_speed(self, params) -> np.ndarray:
        """How fast each of the arm's 7 servos moves its joint towards a target step, relative
        to the MJCF's: its gain over the joint's damping plus the servo's own (``kv``), in
        ``params`` (``PhysParams``, e.g. sysid's) over the nominal values'. The arm's controller
        sets targets a step from the *measured* joints, so in steady motion a joint covers that
        step times ``gain / damping`` per second: the quantity the exciting motions pin down
        (spatula twin 2: each joint's within 6 %, where gain and damping apart were 17-44 % off;
        README, stop 61)."""
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
        configured; ``System.objects["controller"]["joint_speed"]`` carries it."""
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
        from images (``System.objects["tool"]``). The simulator's ``tool`` body moves (its
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
        self.__dict__.pop("renderer", None)

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

    # ------------------------------------------------------------------ images
    @functools.cached_property
    def renderer(self):
        """The differentiable renderer of this task's scene (``twinrl.render.Renderer``)."""
        from twinrl.render import Renderer

        return Renderer.create(self.sim.mj_model, shadows=False)

    def render(self, state, coords: jax.Array | None = None, *, tau: float = 0.0,
               size: int | None = None):
        """``twinrl.render.Images`` of ``state`` from the mount camera at ``coords``
        (unconstrained mount coordinates, default ``mount.default``): RGB, depth, segmentation,
        and soft coverage when ``tau > 0``. Differentiable w.r.t. ``coords`` and the state."""
        from twinrl.render import Geoms

        coords = jnp.asarray(self.mount.default if coords is None else coords, jnp.float32)
        n = int(size or self.config.image_size)
        cam = self.mount.camera(coords, n, n)
        data = state.pipeline_state if hasattr(state, "pipeline_state") else state
        model = self.sim.model_with(self.params)
        return self.renderer.render(cam, Geoms.from_mjx(model, data), tau=tau)

    def image_observation(self, state, coords: jax.Array | None = None, *, size: int | None = None,
                          tau: float = 0.0, keys=None) -> dict:
        """What a robot has (``observation_from_image``) when the simulator renders ``state`` from
        the mount at ``coords``: the target mask is the target geoms' share of each pixel (the
        renderer's coverage: the hard 0/1 mask at ``tau == 0``, soft and differentiable in the
        pose at ``tau > 0``). The image actor's and the sensing Q's observation
        (``twinrl.learn.imitation``, ``twinrl.learn.sensing``). ``keys``: only these entries
        (``observation_from_image``)."""
        coords = jnp.asarray(self.mount.default if coords is None else coords, jnp.float32)
        img = self.render(state, coords, tau=tau, size=size)
        mask = jnp.sum(img.weights[..., self._target_columns], axis=-1)
        return self.observation_from_image(state.obs[:2 * N_JOINTS], coords, img.rgb, img.depth,
                                           mask, keys=keys)

    def observation_from_image(self, joints, coords, rgb, depth, mask, keys=None) -> dict:
        """The image observation's layout, one for the simulator's renders and the real camera's
        frames (``twinrl.sim2real.active``): ``{"state": joint angles and velocities (14,),
        "camera": the commanded pose as fractions (3,) of the mount's azimuth, elevation and
        distance ranges (bounded, so an ascent of Q cannot push a network's input outside what it
        was trained on), "pixels/mount": (n, n, 5) RGB, depth (m) and the target's mask, "tool":
        the tool point (``tool_pose``) of the measured joints (3,), "target":
        ``target_cloud`` of the depth and mask, back-projected from the commanded pose (7,),
        "reach": the target cloud's mean minus the tool point (3,; 0 where the target is not
        seen),
        "pose": the target's joints fitted to that cloud (``fit_target_pose``) and "estimate":
        the privileged observation of the state they and the joints give (``estimated_state``;
        the tool at the identified grasp: ``observe(..., nominal=False)``)
        and "support": how much the fit stands on (2,): log(1 + target pixels) and the fit's RMS
        distance (mm) of those pixels' points from the fitted surfaces (the last three for tasks
        with ``target_joints`` only)}``. The camera is the mount's, hand-eye
        calibration included. ``keys``: only these entries, and only their work traced (the pose
        fit is most of it); default all."""
        n = depth.shape[0]
        pixels = jnp.concatenate([rgb, depth[..., None], mask[..., None]], axis=-1)
        cam = self.mount.camera(coords, n, n)
        tool, cloud = self.tool_point(joints[:N_JOINTS]), target_cloud(cam, depth, mask)
        out = {"state": joints, "camera": jax.nn.sigmoid(coords), "pixels/mount": pixels,
               "tool": tool, "target": cloud,
               "reach": jnp.where(cloud[6] > 0, cloud[:3] - tool, 0.0)}
        fitted = ("pose", "estimate", "support")
        if self.target_joints and (keys is None or any(k in keys for k in fitted)):
            pose, rms = self.fit_target_pose(joints, cam, depth, mask, with_residual=True,
                                             hinge_grid=int(self.config.pose_hinge_grid))
            out["pose"] = pose
            out["estimate"] = self.pose_estimate(joints, pose)
            out["support"] = jnp.stack([out["target"][6], 1e3 * rms])  # the cloud's count
        if keys is None:
            return out
        missing = [k for k in keys if k not in out]
        if missing:
            raise KeyError(f"{self.name}'s image observation has no {missing}; it has "
                           f"{sorted(out)}")
        return {k: out[k] for k in keys}

    def estimated_state(self, joints, pose):
        """``(qpos, qvel)`` of the measured arm (``joints``: 7 angles, 7 velocities) and the
        target at its fitted ``pose`` (``qpos[target_joints]``; at rest): the state estimate
        a robot has from its encoders and one image, whose ``observe`` is laid out as the
        privileged observation a state policy acts on."""
        dt = joints.dtype
        qpos = jnp.asarray(self.sim.mj_model.qpos0, dt).at[:N_JOINTS].set(joints[:N_JOINTS])
        qpos = qpos.at[np.asarray(self.target_joints)].set(pose)
        qvel = jnp.zeros(self.sim.nv, dt).at[:N_JOINTS].set(joints[N_JOINTS:2 * N_JOINTS])
        return qpos, qvel

    @functools.cached_property
    def _target_hinges(self) -> np.ndarray:
        """Which of ``target_joints`` are hinges (the others slide)."""
        m = self.sim.mj_model
        idx = np.asarray(self.target_joints)
        return np.asarray(m.jnt_type)[np.searchsorted(np.asarray(m.jnt_qposadr), idx)] == 3

    def _wrap_target_pose(self, pose):
        """The target's hinge angles modulo its symmetry (``target_hinge_period``), into
        (-period/2, period/2]: the pose an image can tell."""
        period = jnp.asarray(self.target_hinge_period, pose.dtype)
        return jnp.where(self._target_hinges, pose - period * jnp.round(pose / period), pose)

    def estimate_from_obs(self, obs):
        """The image observation's ``"estimate"`` under perfect perception: the privileged
        observation of the state the measured joints (``obs[:14]``) and the target's true pose
        (``state_from_obs``; at rest, hinges modulo the target's symmetry) give -- what a
        ``"pose"`` actor reads when ``fit_target_pose`` is exact. The residual policy of the
        manipulation loop is trained through a model on it (``twinrl.loop_arm``), which renders
        no images. One observation (``obs`` of shape ``(observation_size,)``)."""
        if not self.target_joints:
            raise ValueError(f"{self.name} has no target_joints: no pose estimate")
        obs = jnp.asarray(obs, jnp.float32)
        pose = self.state_from_obs(obs)[0][np.asarray(self.target_joints)]
        return self.pose_estimate(obs[:2 * N_JOINTS], self._wrap_target_pose(pose))

    def pose_estimate(self, joints, pose):
        """The image observation's ``"estimate"`` of measured ``joints`` (7 angles, 7 velocities)
        and a target ``pose``: the privileged observation (``observe``, the tool at the
        identified grasp) of their ``estimated_state`` -- what a ``"pose"`` actor reads, from
        each frame's fit, a fit kept over the episode (``twinrl.sim2real.active.PoseMemory``) or
        the true pose (``estimate_from_obs``)."""
        return self.observe(*self.estimated_state(joints, pose), nominal=False)

    @exact_matmuls
    def fit_target_pose(self, joints, camera, depth, mask, iters: int = 8,
                        huber: float = 0.004, points: int = 256, with_residual: bool = False,
                        hinge_grid: int = 0):
        """The target's pose (its joints' values, ``qpos[target_joints]``) from one depth image:
        the values that put the target pixels' points, back-projected from ``camera``, on the
        surfaces of the target geoms (their union's signed distance, ``Renderer.sdf``) -- a
        Gauss-Newton fit with a Huber loss (``huber`` m), from the guess that moves the target
        geoms' centroid to the points' mean. Model-based perception: the mean of the visible
        pixels alone is off by the faces a pose shows and the arm hides (peg, 12 starts x 6
        steps x 4 random poses: 19-33 mm median). Differentiable in the camera and the images:
        the derivative is the converged fit's (implicit function theorem on its optimality
        condition), not the unrolled iterations'; zeros where no target pixel shows.
        ``points``: target pixels used (a spread subset); ``joints``: the arm's measured angles
        and velocities (14,). The target geoms must be primitives (not meshes).
        ``with_residual``: return ``(pose, rms)``, the fit's weighted RMS signed distance (m; 0
        where no target pixel shows). ``hinge_grid`` K > 1: also start from the hinges turned
        together to K - 1 more angles spread over their period, each alone and with each slide
        moved by +-2.5 cm (a global search; ``bench/pose_views.py`` measures what it buys)."""
        from twinrl.render import Geoms, primitives
        from twinrl.render.pointcloud import depth_to_points, huber_residual

        sg = jax.lax.stop_gradient
        idx = np.asarray(self.target_joints)
        model = self.sim.model_with(self.params)
        dt = depth.dtype
        pts, w = depth_to_points(camera, depth, mask)
        n = jnp.sum(w)
        # at most `points` of the target's pixels, spread over it (a fixed pseudo-random order
        # breaks the ties of a hard mask: top_k alone would keep the first rows)
        k = min(int(points), w.shape[0])
        order = jnp.asarray(np.random.default_rng(0).random(w.shape[0]) * 1e-3, dt)
        _, pick = jax.lax.top_k(sg(w) + order, k)
        pts, w = pts[pick], w[pick]
        # sqrt(w / sum w), with a zero (not infinite) slope at the pixels that show no target:
        # a soft mask's gradient reaches them
        shown = w > 0
        sw = jnp.where(shown, jnp.sqrt(jnp.where(shown, w, 1.0) / jnp.maximum(jnp.sum(w), 1e-3)),
                       0.0)
        gid = self.target_geom_ids
        types = np.asarray(self.sim.mj_model.geom_type)[gid]
        size = jnp.asarray(model.geom_size, dt)[gid]
        chain = self._target_chain

        def poses(x):  # the target geoms' (xpos, xmat): their own chain, or all of mjx's
            qpos = self.estimated_state(joints, x)[0]
            if chain.supports:
                return chain(model, qpos)
            g = Geoms.from_mjx(model, self.sim.init(qpos))
            return g.xpos[gid], g.xmat[gid]

        def centroid(x):
            return jnp.mean(poses(x)[0], 0)

        def resid(x, pts, sw):  # the signed distance to the union of the target geoms
            xpos, xmat = poses(x)
            d = jnp.stack([primitives.sdf(int(t), (pts - xpos[i]) @ xmat[i], size[i])
                           for i, t in enumerate(types)], -1)
            return sw * huber_residual(jnp.min(d, -1), huber)

        eye = jnp.eye(idx.size, dtype=dt)

        def damped(A):
            return A + 1e-3 * jnp.diag(jnp.diag(A)) + 1e-9 * eye

        # the fit itself sees the data as constants: its derivative is the converged solution's
        # (below), not that of the unrolled iterations (~1e12 through the needle's soft images)
        data = sg(pts), sg(sw)
        x = jnp.zeros(idx.size, dt)
        Jc = jax.jacfwd(centroid)(x)
        # the mean of the points the fit uses (`n` counts every target pixel, more than those
        # where the image shows over `points` of them)
        mean = jnp.sum(sg(w)[:, None] * data[0], 0) / jnp.maximum(jnp.sum(sg(w)), 1e-3)
        x = jnp.linalg.solve(Jc.T @ Jc + 1e-6 * eye, Jc.T @ (mean - centroid(x)))

        def step(_, x):
            r, J = resid(x, *data), jax.jacfwd(resid)(x, *data)
            A = J.T @ J
            return x - jnp.linalg.solve(damped(A), J.T @ r)

        # restarts: the guess, and the guess moved by +-2.5 and +-5 cm (slides) / +-0.3 and
        # +-0.6 rad (hinges) along each joint; the fit with the smallest residual wins
        hinge = self._target_hinges
        delta = jnp.asarray(np.where(hinge, 0.3, 0.025), dt)
        starts = [x[None]] + [x + m * delta * eye for m in (1, -1, 2, -2)]
        if hinge_grid > 1 and hinge.any():
            h = jnp.asarray(hinge, dt)
            slide = (delta * eye)[~hinge]
            for k in range(1, hinge_grid):
                turned = x + (k * self.target_hinge_period / hinge_grid) * h
                starts += [turned[None], turned + slide, turned - slide]
        starts = jnp.concatenate(starts)
        fits = jax.vmap(lambda x: jax.lax.fori_loop(0, iters, step, x))(starts)
        cost = jax.vmap(lambda x: jnp.sum(jnp.square(resid(x, *data))))(fits)
        x = fits[jnp.argmin(cost)]
        # the derivative of the converged fit in the data, by the implicit function theorem on
        # its optimality condition g(x, data) = J'r = 0: dx = -H^-1 dg, H = dg/dx (the loss's
        # full Hessian: the Gauss-Newton J'J alone was 30-40 % off central differences through
        # soft images, whose fits keep large residuals), added with a zero value
        def normal(x, pts, sw):
            return jax.jacfwd(resid)(x, pts, sw).T @ resid(x, pts, sw)

        H = jax.jacfwd(normal)(x, *data)
        r = resid(x, pts, sw)
        dx = -jnp.linalg.solve(H + 1e-3 * jnp.diag(jnp.abs(jnp.diag(H))) + 1e-9 * eye,
                               normal(x, pts, sw))
        x = x + (dx - sg(dx))
        seen = n > 3.0
        x = jnp.where(seen, self._wrap_target_pose(x), 0.0)
        if not with_residual:
            return x
        # the residual at the optimum moves with the data alone (the envelope theorem)
        c = jnp.sum(jnp.square(r))
        r = jnp.sqrt(jnp.min(cost) + (c - sg(c)) + 1e-12)  # weights sum to 1: an RMS (Huber)
        return x, jnp.where(seen, r, 0.0)

    @functools.cached_property
    def target_geom_ids(self) -> np.ndarray:
        """MuJoCo geom ids of ``target_geoms`` (NumPy: built inside a trace, a cached jax array
        would leak it)."""
        return np.asarray([self.sim.mj_model.geom(g).id for g in self.target_geoms])

    @functools.cached_property
    def _target_chain(self):
        """The target geoms' poses from their own chain's joints (``twinrl.physics.chain``):
        a pose fit traces it in milliseconds where ``mjx.kinematics`` takes seconds."""
        from twinrl.physics.chain import GeomChain

        return GeomChain(self.sim.mj_model, self.target_geom_ids)

    @functools.cached_property
    def _target_columns(self) -> np.ndarray:
        drawn = list(self.renderer.geom_ids)
        return np.asarray([drawn.index(i) for i in self.target_geom_ids])

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


def _radical_inverse(k: int, base: int) -> float:
    """The ``k``-th element of van der Corput's sequence in ``base`` (Halton's coordinates)."""
    out, f = 0.0, 1.0 / base
    while k:
        k, d = divmod(k, base)
        out += d * f
        f /= base
    return out
