"""``pendulum_swingup``: swing a torque-limited pendulum from hanging to upright and hold it.

Scene ``pendulum.xml``: one hinge (0 = hanging down, joint limits at +-220 deg), a motor of gear 2
(2 N m at |action| = 1) against a gravity torque of up to 4.2 N m, so the swing-up needs
pumping, the classic first-order-gradient benchmark (PODS, Sec. 5 "pendulum"). The joint limits
make the dynamics non-smooth where the pole hits them, which is why the task is in the suite.

Observation (4): ``[cos th, sin th, th_dot, th / pi]`` -- the raw angle is kept because the limits
make ``th`` and ``th + 2 pi`` different states. Action (1): torque in [-1, 1].
Reward (per step in [0, 1]): ``upright * small_control * small_velocity`` with
``upright = (1 - cos th) / 2``.
Real twin: heavier/lighter bob and pole, different hinge damping and friction, a weaker or
stronger motor, 0-1 steps of latency, angle noise, and an offset camera.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from twinrl.envs.base import Env, PerturbationSpec, TaskConfig, small_control, tolerance

__all__ = ["PendulumSwingup", "PendulumSwingupConfig"]


@dataclasses.dataclass(frozen=True)
class PendulumSwingupConfig(TaskConfig):
    episode_length: int = 250
    """Control steps per episode (250 * 0.02 s = 5 s)."""
    frame_skip: int = 2
    """Physics steps (0.01 s) per control step: control period 0.02 s."""
    reset_angle_noise: float = 0.2
    """Half-width (rad) of the uniform initial angle around hanging down."""
    reset_velocity_noise: float = 0.2
    """Half-width (rad/s) of the uniform initial angular velocity."""
    velocity_margin: float = 8.0
    """Angular velocity (rad/s) at which the small-velocity term has fallen to 0.55."""


class PendulumSwingup(Env):
    scene = "pendulum"
    cameras = ("front",)
    reward_term_names = ("upright", "small_control", "small_velocity")
    perturbation_spec = PerturbationSpec(
        mass_scale=(0.85, 1.2),
        damping_scale=(0.5, 2.0),
        friction_scale=(1.0, 1.0),
        gain_scale=(0.85, 1.05),
        extra_frictionloss=(("hinge", 0.0, 0.02),),
        latency_steps=(0, 1),
        obs_noise_std=(0.002, 0.01),
    )
    Config = PendulumSwingupConfig

    def initial_state(self, rng):
        c = self.config
        k1, k2 = jax.random.split(rng)
        th = jax.random.uniform(k1, (1,), minval=-c.reset_angle_noise, maxval=c.reset_angle_noise)
        thd = jax.random.uniform(k2, (1,), minval=-c.reset_velocity_noise,
                                 maxval=c.reset_velocity_noise)
        return th, thd

    def observe(self, qpos, qvel):
        th, thd = qpos[0], qvel[0]
        return jnp.stack([jnp.cos(th), jnp.sin(th), thd, th / jnp.pi]).astype(jnp.float32)

    def state_from_obs(self, obs):
        # The raw angle th / pi, not atan2(sin, cos): the joint limits make th and th + 2 pi
        # different states.
        obs = jnp.asarray(obs)
        return obs[..., 3:4] * jnp.pi, obs[..., 2:3]

    def reward_terms(self, qpos, qvel, action):
        return {
            "upright": 0.5 * (1.0 - jnp.cos(qpos[0])),
            "small_control": small_control(action),
            "small_velocity": 0.5 * (1.0 + tolerance(qvel[0], self.config.velocity_margin, 0.1)),
        }
