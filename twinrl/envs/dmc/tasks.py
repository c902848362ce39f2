"""The Control Suite tasks: cartpole, pendulum, reacher, finger, cheetah and walker.

Each is the suite's task on the wheel's own model (``suite.suite_xml``): its initial-state
distribution (``initialize_episode``), its observation (the suite's ``OrderedDict`` flattened in
order), its reward rewritten in ``jax.numpy`` (``tests/envs/test_dmc.py`` checks it against
dm_control's ``task.get_reward`` on MuJoCo C states), 1000 control steps at the suite's control
timestep (``frame_skip`` = control timestep / the XML's timestep) and a real twin drawn from its
``perturbation_spec``.

Where a task differs from the suite, and why:

- finger's observation leaves out the two ``touch`` sensors (log contact forces: a function of
  the constraint solve, not of ``(qpos, qvel)``, which is what twinrl's observations are).
- reacher's target is a model parameter in the suite (``geom_pos`` set per episode); here the
  target geom sits on two slide joints (``target_x``, ``target_y``) with no force on them, so
  the target is part of the state, which ``reset`` draws and which stays put.
- cheetah settles for 200 physics steps with zero control at reset as the suite does, on the
  simulator (MJX) rather than MuJoCo C.
- pendulum, reacher and finger's rewards are the suite's sparse ones (``tolerance`` with
  ``margin = 0``: a step, zero gradient); ``reward_margin > 0`` gives them a Gaussian tail of
  that width for first-order learners (the suite's reward at 0, the default).
- the contact tasks (finger, cheetah, walker) run a fixed number of constraint-solver
  iterations (``solver_iterations``, as every twinrl task) instead of the XML's 100-200 with early
  exit; the real twin (MuJoCo C) solves to its own tolerance.
"""

from __future__ import annotations

import dataclasses
import xml.etree.ElementTree as ET

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.envs.base import PerturbationSpec, TaskConfig
from twinrl.envs.dmc.suite import SuiteTask, find, randomize_joints, tolerance

__all__ = ["Cartpole", "CartpoleConfig", "Pendulum", "PendulumConfig", "Reacher", "ReacherConfig",
           "Finger", "FingerConfig", "Cheetah", "CheetahConfig", "Walker", "WalkerConfig"]

_NO_CONTACTS = PerturbationSpec(friction_scale=(1.0, 1.0))
"""The real twin of a model without contacts: masses, damping, gains, latency, noise, camera."""
_CONTACTS = PerturbationSpec()
"""... and of a model with contacts: friction too."""


@dataclasses.dataclass(frozen=True)
class SuiteConfig(TaskConfig):
    episode_length: int = 1000
    """Control steps per episode: the suite's time limit over its control timestep."""
    frame_skip: int = 1
    """Physics steps per control step (the suite's control timestep over the XML's timestep)."""


# ---------------------------------------------------------------------- cartpole
@dataclasses.dataclass(frozen=True)
class CartpoleConfig(SuiteConfig):
    swingup: bool = True
    """``swingup`` (pole hanging down) or ``balance`` (near upright)."""


class Cartpole(SuiteTask):
    """``dmc/cartpole-swingup`` and ``dmc/cartpole-balance``: the suite's smooth reward
    ``upright * centered * small_control * small_velocity``. Observation (5): ``[x, cos th,
    sin th, x_dot, th_dot]``; timestep 0.01 s, RK4, no contacts."""

    domain = "cartpole"
    scene = "dmc/cartpole"
    cameras = ("fixed", "lookatcart")
    reward_term_names = ("upright", "centered", "small_control", "small_velocity")
    perturbation_spec = _NO_CONTACTS
    Config = CartpoleConfig

    def initial_state(self, rng):
        k1, k2, k3 = jax.random.split(rng, 3)
        if self.config.swingup:
            x = 0.01 * jax.random.normal(k1, ())
            th = jnp.pi + 0.01 * jax.random.normal(k2, ())
        else:
            x = jax.random.uniform(k1, (), minval=-0.1, maxval=0.1)
            th = jax.random.uniform(k2, (), minval=-0.034, maxval=0.034)
        return jnp.stack([x, th]), 0.01 * jax.random.normal(k3, (2,))

    def observe(self, qpos, qvel):
        th = qpos[1]
        return jnp.stack([qpos[0], jnp.cos(th), jnp.sin(th), qvel[0], qvel[1]]).astype(jnp.float32)

    def state_from_obs(self, obs):
        obs = jnp.asarray(obs)
        th = jnp.arctan2(obs[..., 2], obs[..., 1])
        return jnp.stack([obs[..., 0], th], -1), obs[..., 3:5]

    def reward_terms(self, qpos, qvel, action):
        a = jnp.clip(action, -1.0, 1.0)
        return {
            "upright": (jnp.cos(qpos[1]) + 1) / 2,
            "centered": (1 + tolerance(qpos[0], margin=2)) / 2,
            "small_control": (4 + tolerance(a[0], margin=1, value_at_margin=0,
                                            sigmoid="quadratic")) / 5,
            "small_velocity": (1 + tolerance(qvel[1], margin=5)) / 2,
        }


# ---------------------------------------------------------------------- pendulum
@dataclasses.dataclass(frozen=True)
class PendulumConfig(SuiteConfig):
    reward_margin: float = 0.0
    """Width of a Gaussian tail on the reward's cos bound (0: the suite's sparse reward)."""


class Pendulum(SuiteTask):
    """``dmc/pendulum-swingup``: reward 1 while the pole is within 8 degrees of upright.
    Observation (3): ``[cos th, sin th, th_dot]`` (the pole's ``zz`` and ``xz``); starts at a
    uniform angle at rest; timestep 0.02 s, no contacts, no joint limits."""

    domain = "pendulum"
    scene = "dmc/pendulum"
    cameras = ("fixed", "lookat")
    reward_term_names = ("upright",)
    perturbation_spec = _NO_CONTACTS
    Config = PendulumConfig

    def initial_state(self, rng):
        return jax.random.uniform(rng, (1,), minval=-jnp.pi, maxval=jnp.pi), jnp.zeros(1)

    def observe(self, qpos, qvel):
        return jnp.stack([jnp.cos(qpos[0]), jnp.sin(qpos[0]), qvel[0]]).astype(jnp.float32)

    def state_from_obs(self, obs):
        obs = jnp.asarray(obs)
        return jnp.arctan2(obs[..., 1], obs[..., 0])[..., None], obs[..., 2:3]

    def reward_terms(self, qpos, qvel, action):
        bound = float(np.cos(np.deg2rad(8)))
        return {"upright": tolerance(jnp.cos(qpos[0]), (bound, 1.0),
                                     margin=self.config.reward_margin)}


# ---------------------------------------------------------------------- reacher
@dataclasses.dataclass(frozen=True)
class ReacherConfig(SuiteConfig):
    target_size: float = 0.05
    """Radius (m) of the target: 0.05 is ``easy``, 0.015 ``hard``."""
    reward_margin: float = 0.0
    """Width (m) of a Gaussian tail on the reward's distance bound (0: the suite's sparse one)."""


def _target_on_slides(root: ET.Element) -> None:
    """The target geom onto two force-free slide joints, so that its place is state."""
    world = root.find("worldbody")
    geom = find(world, "geom", "target")
    world.remove(geom)
    body = ET.SubElement(world, "body", name="target", pos="0 0 0")
    for axis, name in (("1 0 0", "target_x"), ("0 1 0", "target_y")):
        ET.SubElement(body, "joint", name=name, type="slide", axis=axis, damping="0")
    body.append(geom)


class Reacher(SuiteTask):
    """``dmc/reacher-easy``: reward 1 while the finger is within target + finger radius of the
    target. Observation (6): ``[shoulder, wrist, to_target (2), shoulder_dot, wrist_dot]``;
    qpos (4): the arm's two joints, then the target's x and y (module docstring)."""

    domain = "reacher"
    scene = "dmc/reacher"
    cameras = ("fixed",)
    reward_term_names = ("reach",)
    perturbation_spec = _NO_CONTACTS
    Config = ReacherConfig
    edit = staticmethod(_target_on_slides)

    def __init__(self, config=None, params=None, name=None):
        super().__init__(config, params, name)
        self._target, self._finger = self.geom("target"), self.geom("finger")

    def initial_state(self, rng):
        k1, k2, k3 = jax.random.split(rng, 3)
        m = self.sim.mj_model
        qpos = randomize_joints(m, k1, jnp.zeros(m.nq))  # the target's slides: unlimited, kept
        angle = jax.random.uniform(k2, (), minval=0.0, maxval=2 * jnp.pi)
        radius = jax.random.uniform(k3, (), minval=0.05, maxval=0.20)
        qpos = qpos.at[2:4].set(jnp.stack([radius * jnp.sin(angle), radius * jnp.cos(angle)]))
        return qpos, jnp.zeros(m.nv)

    def to_target(self, qpos):
        """Target minus finger, in the plane (the suite's ``finger_to_target``)."""
        x = self.frames(qpos).geom_xpos
        return x[self._target, :2] - x[self._finger, :2]

    def observe(self, qpos, qvel):
        return jnp.concatenate([qpos[:2], self.to_target(qpos), qvel[:2]]).astype(jnp.float32)

    def reward_terms(self, qpos, qvel, action):
        radii = self.config.target_size + float(self.sim.mj_model.geom_size[self._finger, 0])
        dist = jnp.sqrt(jnp.sum(jnp.square(self.to_target(qpos))))
        return {"reach": tolerance(dist, (0.0, radii), margin=self.config.reward_margin)}


# ---------------------------------------------------------------------- finger
@dataclasses.dataclass(frozen=True)
class FingerConfig(SuiteConfig):
    frame_skip: int = 2
    """Control timestep 0.02 s on the XML's 0.01 s."""
    solver_iterations: int | None = 10
    """Fixed constraint-solver iterations of the simulator (the XML asks MuJoCo C for 200)."""
    reward_margin: float = 0.0
    """Width (rad/s) of a Gaussian tail on the spin-velocity bound (0: the suite's sparse one)."""
    reset_candidates: int = 16
    """Random joint angles drawn per reset; the first whose geoms do not interpenetrate is kept
    (the suite redraws until one does not)."""


def _spin_damping(root: ET.Element) -> None:
    """``Spin.initialize_episode``'s model change: hinge damping 0.03."""
    find(root.find("worldbody"), "joint", "hinge").set("damping", "0.03")


class Finger(SuiteTask):
    """``dmc/finger-spin``: reward 1 while the spinner turns faster than 15 rad/s (negative
    sense). Observation (7): ``[proximal, distal, tip - spinner (x, z), the three joint
    velocities]`` (no touch sensors: module docstring)."""

    domain = "finger"
    scene = "dmc/finger"
    cameras = ("cam0", "cam1")
    reward_term_names = ("spin",)
    perturbation_spec = _CONTACTS
    Config = FingerConfig
    edit = staticmethod(_spin_damping)

    def initial_state(self, rng):
        m = self.sim.mj_model
        keys = jax.random.split(rng, int(self.config.reset_candidates))
        cands = jax.vmap(lambda k: randomize_joints(m, k, jnp.asarray(m.qpos0, jnp.float32)))(keys)
        free = ~jax.vmap(self.penetrating)(cands)
        qpos = cands[jnp.argmax(free)]  # the first free draw (the first draw if none is)
        return qpos, jnp.zeros(m.nv)

    def observe(self, qpos, qvel):
        f = self.frames(qpos)
        m = self.sim.mj_model
        tip = f.site_xpos[int(m.site("tip").id)] - f.xpos[self.body("spinner")]
        return jnp.concatenate([qpos[:2], tip[jnp.array([0, 2])], qvel]).astype(jnp.float32)

    def reward_terms(self, qpos, qvel, action):
        return {"spin": tolerance(qvel[2], (-jnp.inf, -15.0), margin=self.config.reward_margin)}


# ---------------------------------------------------------------------- cheetah
@dataclasses.dataclass(frozen=True)
class CheetahConfig(SuiteConfig):
    solver_iterations: int | None = 10
    """Fixed constraint-solver iterations of the simulator (MuJoCo C's default is 100)."""
    settle_steps: int = 200
    """Physics steps with zero control after the random joint angles, before the episode."""


class Cheetah(SuiteTask):
    """``dmc/cheetah-run``: reward ``tolerance(v, (10, inf), margin=10, linear)`` of the
    torso subtree's forward velocity. Observation (17): ``[qpos[1:], qvel]``."""

    domain = "cheetah"
    scene = "dmc/cheetah"
    cameras = ("side", "back")
    reward_term_names = ("run",)
    perturbation_spec = _CONTACTS
    Config = CheetahConfig

    def initial_state(self, rng):
        m = self.sim.mj_model
        lim = np.flatnonzero(m.jnt_limited)
        lo, hi = m.jnt_range[lim].T
        qpos = jnp.asarray(m.qpos0, jnp.float32).at[m.jnt_qposadr[lim]].set(
            jax.random.uniform(rng, (len(lim),), minval=lo, maxval=hi))
        n = int(self.config.settle_steps) // int(self.config.frame_skip)
        if n == 0:
            return qpos, jnp.zeros(m.nv)
        zero = jnp.zeros(m.nu)
        d = jax.lax.fori_loop(0, n, lambda _, d: self.sim.step(d, zero, self.params),
                              self.sim.init(qpos, jnp.zeros(m.nv)))
        return jax.lax.stop_gradient(d.qpos), jax.lax.stop_gradient(d.qvel)

    def observe(self, qpos, qvel):
        return jnp.concatenate([qpos[1:], qvel]).astype(jnp.float32)

    def state_from_obs(self, obs):
        # rootx is not observed (the suite's translation invariance): recovered as 0
        obs = jnp.asarray(obs)
        n = self.sim.nq - 1
        qpos = jnp.concatenate([jnp.zeros(obs.shape[:-1] + (1,), obs.dtype), obs[..., :n]], -1)
        return qpos, obs[..., n:]

    def reward_terms(self, qpos, qvel, action):
        v = self.subtree_linvel(qpos, qvel, "torso")[0]
        return {"run": tolerance(v, (10.0, jnp.inf), margin=10.0, value_at_margin=0,
                                 sigmoid="linear")}


# ---------------------------------------------------------------------- walker
@dataclasses.dataclass(frozen=True)
class WalkerConfig(SuiteConfig):
    frame_skip: int = 10
    """Control timestep 0.025 s on the XML's 0.0025 s."""
    solver_iterations: int | None = 10
    """Fixed constraint-solver iterations of the simulator (MuJoCo C's default is 100)."""
    move_speed: float = 1.0
    """Target forward speed (m/s): 0 ``stand``, 1 ``walk``, 8 ``run``."""


class Walker(SuiteTask):
    """``dmc/walker-walk``: the suite's ``stand * (5 move + 1) / 6`` with ``stand = (3
    standing + upright) / 4``. Observation (24): ``[xx, xz of the 7 bodies' frames, torso height,
    qvel]``; random joint angles (any torso pitch) at reset, as the suite's."""

    domain = "walker"
    scene = "dmc/walker"
    cameras = ("side", "back")
    reward_term_names = ("standing", "upright", "move")
    perturbation_spec = _CONTACTS
    Config = WalkerConfig

    def __init__(self, config=None, params=None, name=None):
        super().__init__(config, params, name)
        self._torso = self.body("torso")

    def initial_state(self, rng):
        m = self.sim.mj_model
        return randomize_joints(m, rng, jnp.asarray(m.qpos0, jnp.float32)), jnp.zeros(m.nv)

    def observe(self, qpos, qvel):
        f = self.frames(qpos)
        orient = f.xmat[1:][:, 0, jnp.array([0, 2])].reshape(-1)
        return jnp.concatenate([orient, f.xpos[self._torso, 2:3], qvel]).astype(jnp.float32)

    def reward_terms(self, qpos, qvel, action):
        f = self.frames(qpos)
        v = self.subtree_linvel(qpos, qvel, "torso")[0]
        speed = float(self.config.move_speed)
        terms = {"standing": tolerance(f.xpos[self._torso, 2], (1.2, jnp.inf), margin=0.6),
                 "upright": (1 + f.xmat[self._torso, 2, 2]) / 2}
        terms["move"] = (tolerance(v, (speed, jnp.inf), margin=speed / 2, value_at_margin=0.5,
                                   sigmoid="linear") if speed else jnp.ones((), v.dtype))
        return terms

    def combine(self, terms):
        stand = (3 * terms["standing"] + terms["upright"]) / 4
        if not self.config.move_speed:
            return stand
        return stand * (5 * terms["move"] + 1) / 6
