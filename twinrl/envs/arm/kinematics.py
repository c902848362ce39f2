"""The arm of the manipulation tasks: its model and its kinematics.

- ``panda.xml`` beside this file is the arm (7 revolute joints, position servos, gravity
  compensated); ``compose(task_xml)`` puts it into a task's scene and attaches the task's ``tool``
  body (peg, spatula, thread) at the flange. The result is one plain MJCF string, the same for MJX
  and for the real twin's MuJoCo C engine.
- ``forward_kinematics`` and ``jacobian`` are the arm's kinematics from Franka's published modified
  Denavit-Hartenberg table (``DH``), in JAX: the controller runs them on measured joint angles
  (as a robot's controller uses its nominal kinematic model), identically in the simulator and on
  the real twin, and ``jax.grad`` goes through them.
- ``ik`` (JAX, for resets) and ``solve_ik`` (NumPy, over restarts, for a task's start posture):
  joint angles that put the tool at a pose.
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np


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


@functools.lru_cache(maxsize=None)
def composed(task_xml: str) -> str:
    """``compose(task_xml)``, cached: every task instance shares one string."""
    return compose(task_xml)


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


def rot_z(angle):
    """Rotation matrix (3, 3) of ``angle`` (rad) about the vertical."""
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


def null_space(J: jax.Array) -> jax.Array:
    """Projector onto the null space of ``J`` (6, 7): a posture motion through it leaves the
    tool where it is (the damped pseudo-inverse's projector would leak into the task space)."""
    eye = jnp.eye(J.shape[1], dtype=J.dtype)
    return eye - J.T @ jnp.linalg.solve(J @ J.T + 1e-8 * jnp.eye(6, dtype=J.dtype), J)


@functools.lru_cache(maxsize=None)
def _ik_fn(tcp, nominal, iters):
    def solve(target, yaw, q0):
        q = ik(target, q0, tcp, nominal, yaw, iters)
        p, R = forward_kinematics(q, tcp)
        R_des = rot_z(yaw) @ jnp.asarray(nominal, q.dtype)
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
    R_des = rot_z(jnp.asarray(yaw, dtype)) @ jnp.asarray(nominal, dtype)
    rest = q_init if posture is None else jnp.asarray(posture, dtype)
    lo, hi = (jnp.asarray(JOINT_RANGE[:, i], dtype) for i in (0, 1))

    def body(_, q):
        p, R, J = kinematics_and_jacobian(q, tcp)
        err = jnp.concatenate([target - p, orientation_error(R, R_des)])
        pinv = J.T @ jnp.linalg.solve(J @ J.T + 1e-4 * jnp.eye(6, dtype=dtype),
                                      jnp.eye(6, dtype=dtype))
        dq = pinv @ err + null_space(J) @ (0.1 * (rest - q))
        return jnp.clip(q + dq, lo, hi)

    return jax.lax.fori_loop(0, iters, body, q_init)
