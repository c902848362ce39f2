"""``peg_insertion``: put the peg held by the arm into a hole whose place on the table is random
(SAM-RL, Lv et al. 2023, Sec. 5.1).

Scene ``peg_insertion.xml``: a 25 mm round peg (a capsule, rounded tip) at the flange, a 32 mm
square hole 50 mm deep in a fixture drawn uniformly in x in [0.44, 0.56] m, y in [-0.1, 0.1] m at
reset (3.5 mm clearance per side). The peg starts 15-25 cm above the table over a random point of
the workspace, pointing down. Control: Cartesian displacement of the peg tip, 3-D, at most 2 cm per
0.04 s step (``CartesianController``), the peg held vertical.

Observation (24, privileged): joint angles (7) and velocities (7), peg tip position (3), hole
top-centre position (3), tip minus hole (3), depth of the tip below the hole's top (1).
Reward (per step, in [0, 1]): ``align * (0.3 + 0.7 insert) * small_control``; ``align`` a Gaussian
bump of the tip's horizontal distance to the hole axis (0.1 at 8 cm), ``insert`` one of the tip's
height above the hole's bottom target (0.1 at 15 cm). Depth pays in proportion to alignment, so
the optimiser centres the peg as it descends; the rounded tip slides off the hole's rim into it.
(Paying depth only within 2 cm of the axis, tried to keep the peg off the fixture's top, left
trajectory optimisation 0 of 25 starts after 20 iterations: too little gradient far from the hole.)
Success: the tip is inside the hole (horizontal distance to its axis below the 16 mm half-width)
and at least 30 mm below the fixture's top (``INSERTED_DEPTH``).

What the camera must reveal: the hole's place (the observation's hole position is privileged;
an image policy must find it). The peg and the arm hide the hole from above and behind, the walls
hide its opening from low elevations.

Real twin: grasp offset of the peg (its position in the hand, +-4 mm, and tilt), friction, masses,
joint damping and servo gains, latency, observation noise, the camera's hand-eye offset.
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

__all__ = ["PegInsertion", "PegInsertionConfig", "INSERTED_DEPTH"]

HOLE_TOP = 0.05
"""Height (m) of the fixture's top: the hole's opening."""
HOLE_HALF_WIDTH = 0.016
INSERTED_DEPTH = 0.03
"""How far (m) below the hole's top the peg's tip must be for success."""
PEG_RADIUS = 0.0125
TCP = (0.0, 0.0, 0.12)
"""The controlled point: the centre of the peg's rounded tip, in the tool frame."""


@dataclasses.dataclass(frozen=True)
class PegInsertionConfig(ArmConfig):
    hole_x: tuple[float, float] = (0.44, 0.56)
    """Range (m) of the fixture's x at reset."""
    hole_y: tuple[float, float] = (-0.1, 0.1)
    """Range (m) of the fixture's y at reset."""
    start_xy_noise: float = 0.08
    """Half-width (m) of the uniform start offset of the peg tip from (0.5, 0)."""
    start_height: tuple[float, float] = (0.15, 0.25)
    """Range (m) of the peg tip's start height above the table."""
    align_margin: float = 0.08
    """Horizontal tip-axis distance (m) at which ``align`` has fallen to 0.1."""
    insert_margin: float = 0.15
    """Tip height above the target depth (m) at which ``insert`` has fallen to 0.1."""


class PegInsertion(ArmTask):
    scene = "peg_insertion"
    task_xml = Path(__file__).with_name("peg_insertion.xml")
    controller = CartesianController(tcp=TCP, max_step=0.02)
    mount = CameraMount(target=(0.5, 0.0, 0.05), azimuth=(-2.2, 2.2), elevation=(0.2, 1.4),
                        distance=(0.4, 0.8), default=(0.0, 0.0, 0.0))
    target_geoms = ("wall_left", "wall_right", "wall_front", "wall_back")
    target_joints = (7, 8)
    reward_term_names = ("align", "insert", "small_control")
    perturbation_spec = dataclasses.replace(ARM_PERTURBATIONS, tool_pos_std=0.004)
    Config = PegInsertionConfig

    def __init__(self, config=None, params=None, name=None):
        super().__init__(config, params, name)
        c = self.config
        mid = np.array([0.5, 0.0, float(np.mean(c.start_height))])
        self._q_start = solve_ik(mid, tcp=TCP)
        self.set_posture(self._q_start)

    # ------------------------------------------------------------------ geometry
    @staticmethod
    def hole(qpos) -> jax.Array:
        """Top centre of the hole (world) from the fixture's slide joints ``qpos[7:9]``."""
        return jnp.stack([qpos[7], qpos[8], jnp.full_like(qpos[7], HOLE_TOP)])

    def initial_state(self, rng):
        c = self.config
        k1, k2, k3, k4 = jax.random.split(rng, 4)
        hole = jnp.stack([jax.random.uniform(k1, (), minval=c.hole_x[0], maxval=c.hole_x[1]),
                          jax.random.uniform(k2, (), minval=c.hole_y[0], maxval=c.hole_y[1])])
        xy = jnp.array([0.5, 0.0]) + jax.random.uniform(
            k3, (2,), minval=-c.start_xy_noise, maxval=c.start_xy_noise)
        z = jax.random.uniform(k4, (), minval=c.start_height[0], maxval=c.start_height[1])
        q = ik(jnp.concatenate([xy, z[None]]), self._q_start, TCP)
        # fixture joints are offsets from its body position (0.5, 0) in the MJCF
        qpos = jnp.concatenate([q, hole - jnp.array([0.5, 0.0])])
        return qpos, jnp.zeros(self.sim.nv)

    def tip_and_hole(self, qpos, nominal: bool = False):
        tip = self.tool_point(qpos, nominal)
        hole = self.hole(qpos) + jnp.array([0.5, 0.0, 0.0], qpos.dtype)
        return tip, hole

    def observe(self, qpos, qvel, nominal: bool = True):
        # the robot reports its peg by its nominal kinematics, as the real twin does; a pose
        # estimate (``nominal=False``) puts it at the identified grasp (``ArmTask.set_grasp``)
        tip, hole = self.tip_and_hole(qpos, nominal=nominal)
        depth = hole[2] - (tip[2] - PEG_RADIUS)
        return jnp.concatenate([qpos[:7], qvel[:7], tip, hole, tip - hole,
                                depth[None]]).astype(jnp.float32)

    def state_from_obs(self, obs):
        """``(qpos, qvel)`` of an observation: the joints, and the fixture's offset from the
        hole's position (the fixture does not move: its velocity is zero)."""
        obs = jnp.asarray(obs)
        qpos = jnp.concatenate([obs[..., :7], obs[..., 17:19] - jnp.array([0.5, 0.0], obs.dtype)],
                               axis=-1)
        zero = jnp.zeros(obs.shape[:-1] + (2,), obs.dtype)
        return qpos, jnp.concatenate([obs[..., 7:14], zero], axis=-1)

    def reward_terms(self, qpos, qvel, action):
        c = self.config
        tip, hole = self.tip_and_hole(qpos)
        target_z = hole[2] - INSERTED_DEPTH - 0.005 + PEG_RADIUS
        return {
            "align": tolerance(tip[:2] - hole[:2], c.align_margin, 0.1, axis=-1),
            "insert": tolerance(tip[2] - target_z, c.insert_margin, 0.1),
            "small_control": small_control(action),
        }

    def combine(self, terms):
        return terms["align"] * (0.3 + 0.7 * terms["insert"]) * terms["small_control"]

    def scripted_action(self, obs: np.ndarray) -> np.ndarray:
        """A hand-written expert from the privileged observation: centre over the hole at 8 cm,
        then descend. For tests and gradient-check scenarios (it drives the peg into the
        fixture); the demonstrations are trajectory optimisation's (``bench/manipulation.py``)."""
        d = np.asarray(obs[20:23], np.float64)  # tip minus hole top
        step = self.controller.max_step
        a = np.zeros(3)
        a[:2] = -d[:2] / step
        a[2] = -1.0 if np.hypot(*d[:2]) < 0.004 else (0.08 - d[2]) / step
        return np.clip(a, -1.0, 1.0).astype(np.float32)

    def success(self, qpos, qvel, tool=None) -> jax.Array:
        """1.0 when the peg's tip is in the hole, ``INSERTED_DEPTH`` below its top, else 0.0.
        ``tool``: the true tip's ``(position, rotation)`` (default: ``tool_pose``'s)."""
        tip, hole = self.tip_and_hole(qpos)
        tip = tip if tool is None else tool[0]
        inside = jnp.sum(jnp.square(tip[:2] - hole[:2])) < HOLE_HALF_WIDTH ** 2
        deep = (tip[2] - PEG_RADIUS) < hole[2] - INSERTED_DEPTH
        return (inside & deep).astype(jnp.float32)
