"""``cartpole_balance`` and ``cartpole_swingup``: a cart on a rail keeps a pole upright.

Scene ``cartpole.xml``: cart on a slide joint pushed by a motor (gear 10: 10 N at |action| = 1),
pole on a hinge (angle 0 = upright). The two tasks differ only in the reset distribution: near
upright (balance) or hanging down (swing-up). Control period 0.02 s, 250 steps (5 s).

Observation (5): ``[x, cos th, sin th, x_dot, th_dot]``. Action (1): cart force in [-1, 1].
Reward (per step in [0, 1]), dm_control's cartpole with smooth factors:
``upright * centered * small_control * small_velocity`` where ``upright = (cos th + 1) / 2``,
``centered = (1 + g(x, 2 m)) / 2``, ``small_control = (4 + 1 - a^2) / 5``,
``small_velocity = (1 + g(th_dot, 5 rad/s)) / 2`` and ``g`` a Gaussian bump (``tolerance``).

Sim versus real, as in the Hybrid Differentiable Simulation study's cartpole: **the simulated cart
rolls frictionlessly** (the MJCF has no friction loss on the slider, so MJX has no friction row
for it at all), **while the real cart has rail friction** (dry friction loss of 0.3-1.2 N on the
slider, which the MuJoCo C engine of the real twin models) **and different joint damping**
(viscous rail damping 0.05-0.3 N s/m that the simulator lacks, hinge damping scaled 0.5-3x).
Masses, motor gain, action latency (0-1 steps), observation noise and the camera pose differ too.
A model that cannot represent the rail friction is what the hybrid (learned residual) dynamics
of ``twinrl.sim2real.hybrid`` is for.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from twinrl.envs.base import Env, PerturbationSpec, TaskConfig, small_control, tolerance

__all__ = ["Cartpole", "CartpoleConfig"]


@dataclasses.dataclass(frozen=True)
class CartpoleConfig(TaskConfig):
    episode_length: int = 250
    """Control steps per episode (250 * 0.02 s = 5 s)."""
    frame_skip: int = 2
    """Physics steps (0.01 s) per control step: control period 0.02 s."""
    swingup: bool = False
    """Start hanging down (swing-up) instead of near upright (balance)."""
    reset_angle_noise: float = 0.1
    """Half-width (rad) of the uniform initial pole angle around its nominal (0 or pi)."""
    reset_position_noise: float = 0.1
    """Half-width (m) of the uniform initial cart position around 0."""
    reset_velocity_noise: float = 0.05
    """Half-width of the uniform initial cart (m/s) and pole (rad/s) velocities."""
    center_margin: float = 2.0
    """Cart distance (m) from the centre at which the centered term has fallen to 0.55."""
    velocity_margin: float = 5.0
    """Pole angular velocity (rad/s) at which the small-velocity term has fallen to 0.55."""


class Cartpole(Env):
    scene = "cartpole"
    cameras = ("front",)
    reward_term_names = ("upright", "centered", "small_control", "small_velocity")
    perturbation_spec = PerturbationSpec(
        mass_scale=(0.85, 1.2),
        damping_scale=(0.5, 3.0),
        friction_scale=(1.0, 1.0),
        gain_scale=(0.85, 1.05),
        extra_damping=(("slider", 0.05, 0.3),),
        extra_frictionloss=(("slider", 0.3, 1.2),),
        latency_steps=(0, 1),
        obs_noise_std=(0.002, 0.01),
    )
    Config = CartpoleConfig

    def initial_state(self, rng):
        c = self.config
        k1, k2, k3 = jax.random.split(rng, 3)
        th0 = jnp.pi if c.swingup else 0.0
        x = jax.random.uniform(k1, (), minval=-c.reset_position_noise, maxval=c.reset_position_noise)
        th = th0 + jax.random.uniform(k2, (), minval=-c.reset_angle_noise,
                                      maxval=c.reset_angle_noise)
        qvel = jax.random.uniform(k3, (2,), minval=-c.reset_velocity_noise,
                                  maxval=c.reset_velocity_noise)
        return jnp.stack([x, th]), qvel

    def observe(self, qpos, qvel):
        x, th = qpos[0], qpos[1]
        return jnp.stack([x, jnp.cos(th), jnp.sin(th), qvel[0], qvel[1]]).astype(jnp.float32)

    def state_from_obs(self, obs):
        # The angle comes back in (-pi, pi]: equal to the recorded one modulo 2 pi, which the
        # dynamics and the observation cannot tell apart (no joint limit on the hinge).
        obs = jnp.asarray(obs)
        th = jnp.arctan2(obs[..., 2], obs[..., 1])
        return jnp.stack([obs[..., 0], th], -1), jnp.stack([obs[..., 3], obs[..., 4]], -1)

    def reward_terms(self, qpos, qvel, action):
        c = self.config
        return {
            "upright": 0.5 * (jnp.cos(qpos[1]) + 1.0),
            "centered": 0.5 * (1.0 + tolerance(qpos[0], c.center_margin, 0.1)),
            "small_control": small_control(action),
            "small_velocity": 0.5 * (1.0 + tolerance(qvel[1], c.velocity_margin, 0.1)),
        }
