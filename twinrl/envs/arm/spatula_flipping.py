"""``spatula_flipping``: slide the spatula held by the arm under a pancake lying against a low
rail and turn it upside down (SAM-RL, Lv et al. 2023, Sec. 5.2).

Scene ``spatula_flipping.xml``: a spatula (a flat blade 90 x 80 mm, 3 mm thick, on a handle
pointing forward and down at 70 degrees) at the flange; a pancake (a flat cake 70 x 70 mm, 12 mm
thick, 80 g, rounded along its near and far rims, a dark mark on its top) on the table against a
rail (three studs 10 mm high) drawn at x in [0.66, 0.72] m, y in [-0.08, 0.08] m; the pancake
lies 1-4 mm in front of the rail, up to 2 cm off its centre. The blade's edge starts 12-18 cm
short of the pancake, 2-5 cm above the table. Control (``CartesianController``): displacement of
the blade's leading edge, 3-D, at most 2 cm per 0.04 s step; the spatula is held at its nominal
angle.

Mechanism: the blade's edge wedges under the pancake's round near rim; lifting it turns the
pancake about its far rim, which the rail holds; past vertical it falls over, onto the rail and
the table beyond it, upside down. Shapes and contacts are chosen for their derivatives: the blade
collides as three thin capsules along it, the pancake as five capsules across it, the rail as
spheres, so every pair is plane-capsule, capsule-capsule (near perpendicular) or sphere-capsule,
MJX's closed-form colliders, continuous in the poses. (The first design's ellipsoid pancake and
round blade went through MJX's SDF search, and the flip's gradients were kinked and exploded; the
second's box blade on a box pancake went through MJX's box-box SAT, whose contact points jump: a
1e-9 change of one action changed a 30-step rollout loss by 0.15.) The pancake's contacts are
soft (timeconst 3 physics steps).

Observation (31, privileged): joint angles (7) and velocities (7), the blade's edge (3), the
pancake's centre (3), its up axis (3) and velocity (3), the rail's x, y (2), the point under the
pancake (2 cm short of its centre, at the table) minus the blade's edge (3). Reward (per step,
in [0, 1]): ``(0.25 reach + 0.75 flip * far_rim_down) * small_control``; ``reach`` a Gaussian bump
of the distance from the blade's edge to that point (0.1 at 12 cm): reaching it means sliding under
the pancake's near half; ``flip`` the pancake's turn towards the rail over pi (``turn``: 0 lying as
it started, 1/2 standing on its far rim, 1 upside down), which grows in proportion to the near
rim's lift from the first millimetre; ``far_rim_down`` a Gaussian bump of the far rim's lift off
the table (0.1 at 2 cm) until the pancake passes vertical, so that turning pays only about the far
rim. Both choices come from where trajectory optimisation (``bench/manipulation.py``, 20 starts,
20 first-order iterations from zero actions) got stuck: with the point 1 cm *past* the centre and
no far-rim term, it slid the blade fully under and carried the pancake, tilted by the blade's own
10 degrees (25 % solved); with the point 2 cm short, 55 %; with the far-rim term too, 60 %, and
the failures left are mostly the blade resting under the pancake without lifting.
Success: the pancake is upside down (up axis' z below -0.9) and resting (centre below 15 mm).

What the camera must reveal: the pancake's pose and which side is up (the mark on its top); the
blade, the arm and the rail hide the pancake's near rim from some poses, and from above a tilted
pancake's side is hard to tell.

Real twin: grasp offset of the spatula (its position in the hand +-3 mm, tilt), friction (the
blade's on the pancake decides whether its edge wedges under the rim or jams), the pancake's
mass, joint damping and servo gains, latency, observation noise, the camera's hand-eye offset.
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

__all__ = ["SpatulaFlipping", "SpatulaFlippingConfig"]

_C, _S = np.cos(np.deg2rad(70.0)), np.sin(np.deg2rad(70.0))
SPATULA = ((_S, 0.0, _C), (0.0, -1.0, 0.0), (_C, 0.0, -_S))
"""Tool orientation with the handle (tool z) pointing forward (+x) and down at 70 degrees (at
45 degrees the Panda reaches the table near the pancake only at its joint limits)."""
TCP = (0.07361, 0.0, 0.1925)
"""The blade's leading edge in the tool frame."""
STOPPER_ORIGIN = np.array([0.69, 0.0])
PANCAKE_RADIUS = 0.035
"""Half the pancake's length along x (its rims' outer faces), m."""
PANCAKE_HALF_THICKNESS = 0.006
UNDER = -0.02
"""Where (m along x from the pancake's centre) the reward's ``reach`` leads the blade's edge: 1.5 cm
inside its near rim (module docstring)."""
FAR_RIM = 0.029
"""The far rim's axis along the pancake's local x from its centre, m."""
STOPPER_HALF_DEPTH = 0.005
"""Half the rail's depth along x, m."""


@dataclasses.dataclass(frozen=True)
class SpatulaFlippingConfig(ArmConfig):
    episode_length: int = 60
    """Control steps per episode (2.4 s)."""
    stopper_x: tuple[float, float] = (0.66, 0.72)
    """Range (m) of the stopper rail's x at reset."""
    stopper_y: tuple[float, float] = (-0.08, 0.08)
    """Range (m) of the stopper rail's y at reset."""
    gap: tuple[float, float] = (0.001, 0.004)
    """Range (m) of the gap between the pancake's rim and the stopper at reset."""
    pancake_y_noise: float = 0.02
    """Half-width (m) of the pancake's uniform sideways offset from the stopper's centre."""
    start_back: tuple[float, float] = (0.12, 0.18)
    """Range (m) of how far short of the pancake's centre (along x) the blade's edge starts."""
    start_height: tuple[float, float] = (0.02, 0.05)
    """Range (m) of the blade edge's start height above the table."""
    start_side: tuple[float, float] = (0.0, 0.0)
    """Range (m) of the blade edge's start offset sideways (y) from the pancake's centre. In
    line by default; an offset makes demonstrations that correct sideways, which an actor cloned
    from in-line starts never saw (README: the spatula's image actor on the real twins)."""
    reach_margin: float = 0.12
    """Distance (m) from the blade's edge to the point under the pancake at which ``reach`` has
    fallen to 0.1."""
    far_rim_margin: float = 0.02
    """Lift (m) of the pancake's far rim off the table at which ``flip`` is scaled by 0.1 (while
    the pancake has not passed vertical): turning pays only about the far rim."""
    expert_push: float = 0.1
    """The scripted expert's forward action while it lifts."""
    expert_lift: float = 0.35
    """The scripted expert's upward action while it lifts."""
    expert_tip: float = 0.9
    """Turn (rad) past which the scripted expert stops lifting and pushes forward."""
    expert_shove: float = 0.4
    """The scripted expert's forward action once the pancake stands."""
    expert_release: float = 1.9
    """Turn (rad) past which the scripted expert holds still and lets the pancake fall."""


class SpatulaFlipping(ArmTask):
    scene = "spatula_flipping"
    task_xml = Path(__file__).with_name("spatula_flipping.xml")
    controller = CartesianController(tcp=TCP, nominal=SPATULA, max_step=0.02)
    mount = CameraMount(target=(0.62, 0.0, 0.02), azimuth=(-2.2, 2.2), elevation=(0.2, 1.4),
                        distance=(0.35, 0.75), default=(0.0, 0.0, 0.0))
    target_geoms = ("pancake_top",)  # the mark that tells which side is up
    reward_term_names = ("reach", "flip", "far_rim_down", "small_control")
    perturbation_spec = dataclasses.replace(ARM_PERTURBATIONS, friction_scale=(0.8, 1.25))
    Config = SpatulaFlippingConfig

    def __init__(self, config=None, params=None, name=None):
        super().__init__(config, params, name)
        c = self.config
        mid = np.array([STOPPER_ORIGIN[0] - 0.04 - np.mean(c.start_back), 0.0,
                        np.mean(c.start_height)])
        self._q_start = solve_ik(mid, tcp=TCP, nominal=SPATULA)
        self.set_posture(self._q_start)

    # ------------------------------------------------------------------ geometry
    @staticmethod
    def turn(up) -> jax.Array:
        """How far (rad) the pancake has turned over towards the rail: 0 flat as it started, pi/2
        standing on its far rim, pi upside down (the angle of its up axis in the x-z plane,
        continuous except when tilted backwards past vertical, which a flip never does). Its
        derivative at 0 is 1, where ``(1 - up_z) / 2``'s is 0: lifting the near rim pays at once."""
        return 0.5 * jnp.pi - jnp.arctan2(up[2], up[0])

    @staticmethod
    def pancake(qpos) -> tuple[jax.Array, jax.Array]:
        """The pancake's centre (3,) and up axis (3,) (its local z in the world)."""
        w, x, y, z = qpos[12], qpos[13], qpos[14], qpos[15]
        up = jnp.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
        return qpos[9:12], up

    def edge(self, qpos, nominal: bool = False) -> jax.Array:
        return self.tool_point(qpos, nominal)

    @staticmethod
    def under(centre) -> jax.Array:
        """Where the blade's edge should go: under the pancake's near half, 2 cm short of its
        centre, at the table (module docstring: why not at the rim, nor past the centre)."""
        return centre + jnp.array([UNDER, 0.0, -PANCAKE_HALF_THICKNESS], centre.dtype)

    @staticmethod
    def far_rim_lift(qpos) -> jax.Array:
        """Height (m) of the pancake's far rim (its axis) above where it lies on the table."""
        w, x, y, z = qpos[12], qpos[13], qpos[14], qpos[15]
        return jnp.maximum(qpos[11] + FAR_RIM * 2 * (x * z - w * y) - PANCAKE_HALF_THICKNESS,
                           0.0)

    def approach_point(self, qpos) -> jax.Array:
        """1 cm short of the pancake's near rim, 2 mm above the table: where trajectory
        optimisation's approach guess (``approach_plan``) takes the blade's edge."""
        centre, _ = self.pancake(qpos)
        return centre + jnp.array([-(PANCAKE_RADIUS + 0.01), 0.0,
                                   0.002 - PANCAKE_HALF_THICKNESS], centre.dtype)

    def initial_state(self, rng):
        c = self.config
        k = jax.random.split(rng, 7)
        u = lambda key, lo_hi: jax.random.uniform(key, (), minval=lo_hi[0], maxval=lo_hi[1])
        stopper = jnp.stack([u(k[0], c.stopper_x), u(k[1], c.stopper_y)])
        centre = jnp.stack([
            stopper[0] - STOPPER_HALF_DEPTH - PANCAKE_RADIUS - u(k[2], c.gap),
            stopper[1] + u(k[3], (-c.pancake_y_noise, c.pancake_y_noise)),
            jnp.asarray(PANCAKE_HALF_THICKNESS)])
        tip = jnp.stack([centre[0] - u(k[4], c.start_back), centre[1] + u(k[6], c.start_side),
                         u(k[5], c.start_height)])
        q = ik(tip, self._q_start, TCP, SPATULA, iters=40)
        qpos = jnp.concatenate([q, stopper - jnp.asarray(STOPPER_ORIGIN, stopper.dtype), centre,
                                jnp.array([1.0, 0.0, 0.0, 0.0], centre.dtype)])
        return qpos, jnp.zeros(self.sim.nv)

    def observe(self, qpos, qvel, nominal: bool = True):
        # the robot reports its blade by its nominal kinematics, as the real twin does; a pose
        # estimate (``nominal=False``) puts it at the identified grasp (``ArmTask.set_grasp``)
        edge = self.edge(qpos, nominal=nominal)
        centre, up = self.pancake(qpos)
        stopper = jnp.asarray(STOPPER_ORIGIN, qpos.dtype) + qpos[7:9]
        return jnp.concatenate([qpos[:7], qvel[:7], edge, centre, up, qvel[9:12], stopper,
                                self.under(centre) - edge]).astype(jnp.float32)

    def state_from_obs(self, obs):
        """``(qpos, qvel)`` of an observation, up to what it does not say: the pancake's spin
        about its own axis (its orientation is the smallest turn from flat to its up axis) and its
        angular velocity (zero). The stopper does not move."""
        obs = jnp.asarray(obs)
        up = obs[..., 20:23]
        # the quaternion of the smallest rotation taking z to ``up``: (1 + u_z, -u_y, u_x, 0)
        quat = jnp.stack([1.0 + up[..., 2], -up[..., 1], up[..., 0], jnp.zeros_like(up[..., 0])],
                         axis=-1)
        flipped = jnp.array([0.0, 1.0, 0.0, 0.0], obs.dtype)
        quat = jnp.where(up[..., 2:3] > -1.0 + 1e-6, quat, flipped)
        quat = quat / jnp.linalg.norm(quat, axis=-1, keepdims=True)
        qpos = jnp.concatenate([obs[..., :7],
                                obs[..., 26:28] - jnp.asarray(STOPPER_ORIGIN, obs.dtype),
                                obs[..., 17:20], quat], axis=-1)
        zero = lambda n: jnp.zeros(obs.shape[:-1] + (n,), obs.dtype)
        return qpos, jnp.concatenate([obs[..., 7:14], zero(2), obs[..., 23:26], zero(3)], axis=-1)

    def reward_terms(self, qpos, qvel, action):
        centre, up = self.pancake(qpos)
        turn = self.turn(up)
        down = tolerance(self.far_rim_lift(qpos), self.config.far_rim_margin, 0.1)
        return {
            "reach": tolerance(self.under(centre) - self.edge(qpos), self.config.reach_margin,
                               0.1, axis=-1),
            "flip": jnp.clip(turn / jnp.pi, 0.0, 1.0),
            # past vertical the far rim is the one it falls over: no longer asked to stay down
            "far_rim_down": jnp.where(turn < 0.5 * jnp.pi, down, 1.0),
            "small_control": small_control(action),
        }

    def combine(self, terms):
        return ((0.25 * terms["reach"] + 0.75 * terms["flip"] * terms["far_rim_down"])
                * terms["small_control"])

    def scripted_action(self, obs: np.ndarray) -> np.ndarray:
        """A hand-written expert from the privileged observation: put the blade's edge 1 cm short
        of the pancake's near rim on the table, slide under the rim, then push on and lift (the
        rail holds the far rim, the pancake turns over it) until it stands past vertical, and
        hold still while it falls over. For tests and gradient-check scenarios; the
        demonstrations are trajectory optimisation's."""
        o = np.asarray(obs, np.float64)
        under, up = o[28:31], o[20:23]      # the point under the pancake minus the blade's edge
        rim = under - np.array([UNDER + PANCAKE_RADIUS + 0.01, 0.0, 0.0])  # 1 cm short of it
        turn = float(self.turn(up))
        step = self.controller.max_step
        if turn > self.config.expert_release:  # past vertical: hold still, it falls over
            a = np.zeros(3)
        elif turn < 0.15 and (abs(rim[1]) > 0.01 or rim[0] > 0.015):  # to the near rim
            a = np.array([rim[0], rim[1], rim[2] + 0.002]) / step
        elif turn < 0.15 and under[0] - UNDER > 0.01:  # slide under, to 1 cm short of its centre
            a = np.array([0.6, rim[1] / step, -0.05])
        elif turn < self.config.expert_tip:  # under it: lift, it turns about its far rim
            a = np.array([self.config.expert_push, rim[1] / step, self.config.expert_lift])
        else:  # standing up: push it forward past vertical
            a = np.array([self.config.expert_shove, rim[1] / step, 0.0])
        return np.clip(a, -1.0, 1.0).astype(np.float32)

    def success(self, qpos, qvel, tool=None) -> jax.Array:
        """1.0 when the pancake lies upside down on the table, else 0.0 (the tool plays no
        part)."""
        centre, up = self.pancake(qpos)
        return ((up[2] < -0.9) & (centre[2] < 0.015)).astype(jnp.float32)
