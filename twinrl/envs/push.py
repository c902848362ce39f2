"""``push``: push a box across a plane onto a goal with a sphere, through contacts.

Scene ``push.xml``: a sphere pusher on two actuated slide joints (x, y; 2-D action), a free box
resting on a plane with sliding friction, a goal disc at (0.5, 0). The box moves only through
pusher-box contact and is braked by box-floor friction, so every useful gradient passes through
the contact solve (SAM-RL's and PODS's manipulation setting). Control period 0.05 s, 200 steps.

Observation (12): pusher ``[x, y, x_dot, y_dot]``, box ``[x, y, cos yaw, sin yaw, x_dot, y_dot]``,
goal minus box ``[dx, dy]``. Action (2): pusher forces in [-1, 1].
Reward (per step in [0, 1]): ``(0.75 near_goal + 0.25 reach) * small_control``, with
``near_goal`` a Gaussian bump of the box-goal distance, ``reach`` one of the pusher-box distance.
Real twin: box and pusher masses, floor and box friction, pusher damping and motor gain differ;
0-2 steps of latency; position noise; an offset camera.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.envs.base import Env, PerturbationSpec, TaskConfig, small_control, tolerance

__all__ = ["Push", "PushConfig"]


@dataclasses.dataclass(frozen=True)
class PushConfig(TaskConfig):
    episode_length: int = 200
    """Control steps per episode (200 * 0.05 s = 10 s)."""
    frame_skip: int = 5
    """Physics steps (0.01 s) per control step: control period 0.05 s."""
    reset_box_noise: float = 0.04
    """Half-width (m) of the uniform initial box x/y offset from (0.15, 0)."""
    reset_yaw_noise: float = 0.3
    """Half-width (rad) of the uniform initial box yaw."""
    reset_pusher_noise: float = 0.05
    """Half-width (m) of the uniform initial pusher x/y offset from the origin."""
    goal_margin: float = 0.4
    """Box-goal distance (m) at which ``near_goal`` has fallen to 0.1."""
    reach_margin: float = 0.3
    """Pusher-box centre distance (m) at which ``reach`` has fallen to 0.1."""
    goal_weight: float = 0.75
    """Weight of ``near_goal`` against ``reach`` (which gets ``1 - goal_weight``)."""

    def __post_init__(self):
        super().__post_init__()
        if not 0.0 <= self.goal_weight <= 1.0:
            raise ValueError(f"goal_weight must be in [0, 1], got {self.goal_weight}")


def _yaw_cos_sin(quat):
    """cos and sin of the yaw of a box quaternion ``(w, x, y, z)`` (leading axis): exact for a
    yaw-only rotation, smooth in the quaternion everywhere (NumPy or JAX arrays)."""
    w, x, y, z = quat[0], quat[1], quat[2], quat[3]
    return 1.0 - 2.0 * (y * y + z * z), 2.0 * (w * z + x * y)


class Push(Env):
    scene = "push"
    cameras = ("top",)
    reward_term_names = ("near_goal", "reach", "small_control")
    perturbation_spec = PerturbationSpec(
        mass_scale=(0.8, 1.3),
        damping_scale=(0.7, 1.4),
        friction_scale=(0.7, 1.3),
        gain_scale=(0.85, 1.1),
        latency_steps=(0, 1, 2),
        obs_noise_std=(0.001, 0.005),
    )
    Config = PushConfig

    def __init__(self, config=None, params=None, name=None):
        super().__init__(config, params, name)
        m = self.sim.mj_model
        self.goal = jnp.asarray(np.array(m.geom("goal").pos[:2]), jnp.float32)
        self._box_qpos0 = np.array(m.qpos0[2:9])
        self._box_half = float(m.geom("box").size[0])
        self._pusher_radius = float(m.geom("pusher").size[0])

    def initial_state(self, rng):
        c = self.config
        k1, k2, k3 = jax.random.split(rng, 3)
        box_xy = jnp.asarray(self._box_qpos0[:2]) + jax.random.uniform(
            k1, (2,), minval=-c.reset_box_noise, maxval=c.reset_box_noise)
        yaw = jax.random.uniform(k2, (), minval=-c.reset_yaw_noise, maxval=c.reset_yaw_noise)
        quat = jnp.stack([jnp.cos(yaw / 2), 0.0, 0.0, jnp.sin(yaw / 2)])
        pusher = jax.random.uniform(k3, (2,), minval=-c.reset_pusher_noise,
                                    maxval=c.reset_pusher_noise)
        qpos = jnp.concatenate([pusher, box_xy, jnp.asarray(self._box_qpos0[2:3]), quat])
        return qpos, jnp.zeros(self.sim.nv)

    def observe(self, qpos, qvel):
        cos_yaw, sin_yaw = _yaw_cos_sin(qpos[5:9])
        box = qpos[2:4]
        return jnp.concatenate([
            qpos[0:2], qvel[0:2], box, jnp.stack([cos_yaw, sin_yaw]), qvel[2:4], self.goal - box,
        ]).astype(jnp.float32)

    def state_from_obs(self, obs):
        raise NotImplementedError(
            "Push.state_from_obs: the observation does not determine the state -- the box's "
            "height, roll, pitch, vertical velocity and angular velocity (qpos[4], the quaternion "
            "beyond yaw, qvel[4:8]) are not observed, so a simulated window cannot start from a "
            "recorded observation; identify push from full states or with a state estimator")

    def excitation_policy(self, rng: np.random.Generator):
        """A closed-loop excitation for identifying push (``twinrl.real2sim.sysid.collect``):
        open-loop random forces rarely touch the box (two 10 s episodes of held random levels
        never moved it), so its mass and friction would be invisible. Repeated strokes: the
        pusher goes behind the box (free motion: its gain and damping), pushes it along a random
        direction that keeps it near the start with a random force for a random time (mass and
        friction while accelerating and sliding), then backs off and lets it slide to a stop
        (friction alone). Returns ``policy(obs, t) -> action``; works on the task's observation
        and on ``observation="state"``."""
        state = {}  # the stroke in progress; new_stroke fills it at t = 0
        full = self.config.observation == "state"
        reach = 0.05 + 0.03 + 0.02  # box half-size + pusher radius + a gap

        def positions(obs):
            o = np.asarray(obs, np.float64)
            if full:  # [qpos (9), qvel (8)]
                return o[0:2], o[9:11], o[2:4]
            return o[0:2], o[2:4], o[4:6]

        def new_stroke(box):
            home = np.asarray(self._box_qpos0[:2]) - box  # drift back towards the start
            ang = np.arctan2(home[1], home[0]) + rng.uniform(-1.2, 1.2) if np.linalg.norm(
                home) > 0.1 else rng.uniform(-np.pi, np.pi)
            state.update(phase="approach", n=0, dir=np.array([np.cos(ang), np.sin(ang)]),
                         force=rng.uniform(0.55, 1.0), push=int(rng.integers(4, 14)),
                         rest=int(rng.integers(3, 8)))

        def policy(obs, t):
            p, v, box = positions(obs)
            if t == 0:
                new_stroke(box)
            d = state["dir"]
            state["n"] += 1
            if state["phase"] == "approach":
                target = box - reach * d
                a = 8.0 * (target - p) - 1.0 * v
                if np.linalg.norm(target - p) < 0.02 or state["n"] > 30:
                    state.update(phase="push", n=0)
            elif state["phase"] == "push":
                side = np.array([-d[1], d[0]])
                a = state["force"] * d + 2.0 * np.dot(box - p, side) * side
                if state["n"] >= state["push"]:
                    state.update(phase="release", n=0)
            else:  # back off, then rest: the box slides to a stop on its own
                a = -0.6 * d if state["n"] <= 2 else -1.0 * v
                if state["n"] >= state["rest"]:
                    new_stroke(box)
            return np.clip(a, -1.0, 1.0).astype(np.float32)

        return policy

    def pusher_clear(self, obs, margin: float = 0.005) -> np.ndarray:
        """Whether the pusher is more than ``margin`` (m) from the box in each observation
        (``...`` x this env's observation; the task's or ``observation="state"``), from the planar
        pose: the gap between the sphere and the box's square footprint. Identification uses it
        to fit the pusher's own gains and damping on windows where it touches nothing
        (``twinrl.real2sim.sysid.Windows.select``) before the box's mass and friction."""
        o = np.asarray(obs, np.float64)
        if o.shape[-1] != self.observation_size:
            raise ValueError(f"pusher_clear: observations have {o.shape[-1]} entries; this env's "
                             f"have {self.observation_size}")
        if self.config.observation == "state":  # [qpos (9), qvel (8)]
            (c, s), box = _yaw_cos_sin(np.moveaxis(o[..., 5:9], -1, 0)), o[..., 2:4]
        else:  # observe's cos/sin of yaw
            c, s, box = o[..., 6], o[..., 7], o[..., 4:6]
        n = np.maximum(np.hypot(c, s), 1e-9)  # unit length under a tilt too
        c, s = c / n, s / n
        d = o[..., 0:2] - box
        local = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)
        outside = np.maximum(np.abs(local) - self._box_half, 0.0)
        return np.linalg.norm(outside, axis=-1) - self._pusher_radius > margin

    def reward_terms(self, qpos, qvel, action):
        c = self.config
        box = qpos[2:4]
        return {
            "near_goal": tolerance(box - self.goal, c.goal_margin, 0.1, axis=-1),
            "reach": tolerance(qpos[0:2] - box, c.reach_margin, 0.1, axis=-1),
            "small_control": small_control(action),
        }

    def combine(self, terms):
        w = self.config.goal_weight
        return (w * terms["near_goal"] + (1.0 - w) * terms["reach"]) * terms["small_control"]
