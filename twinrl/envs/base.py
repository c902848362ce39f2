"""The functional task API: ``Env`` and ``State``, compatible with Brax's.

A task is a ``Sim`` (an MJCF compiled for MJX) plus what turns physics into a learning problem:
the reset distribution, the observation, the action bounds, a smooth reward made of named terms,
the episode length, the cameras, and the spec of how its real twin differs (``PerturbationSpec``).
``Env`` subclasses ``brax.envs.base.Env`` and its ``State`` *is* Brax's ``State``, so Brax's
wrappers (``brax.envs.wrappers.training.wrap``) and trainers (``brax.training.agents.ppo``) take
our tasks unmodified; the ``pipeline_state`` is the ``mjx.Data``.

Everything here is a pure function of pytrees: ``reset(rng)`` and ``step(state, action)`` jit,
vmap and differentiate end to end (the physics through ``twinrl.physics.solver``'s
fixed-iteration constraint solve, the reward because every term is smooth). This is what
first-order methods need (PODS, Sec. 3; SHAC, Sec. 4: gradients of the return w.r.t. actions).

The task-specific hooks are written on ``(qpos, qvel)`` rather than on ``mjx.Data``, so the real
twin (``twinrl.real.twin``, MuJoCo C engine, NumPy state) evaluates *the same* observation and
reward functions as the simulator.
"""

from __future__ import annotations

import abc
import copy
import dataclasses
import types
from typing import ClassVar, Mapping

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs import base as brax_base
from mujoco import mjx

from twinrl.physics import PhysParams, Sim
from twinrl.physics.collision import check_contacts

__all__ = ["Env", "State", "TaskConfig", "PerturbationSpec", "tolerance", "small_control",
           "replace_config"]

State = brax_base.State
"""Brax's environment state: ``pipeline_state`` (``mjx.Data``), ``obs``, ``reward``, ``done``,
``metrics`` (``reward/<term>`` per reward term) and ``info`` (left to wrappers)."""


@dataclasses.dataclass(frozen=True)
class TaskConfig:
    """Fields every task has; tasks subclass this with their own (each with a docstring)."""

    episode_length: int = 250
    """Control steps per episode (the trainer's ``episode_length``; the real twin truncates here)."""
    frame_skip: int = 2
    """Physics steps of the scene's timestep per control step (control period = dt * frame_skip)."""
    observation: str = "task"
    """``"task"``: the task's observation (what a policy sees); ``"state"``: the full physical
    state ``[qpos, qvel]``, as a motion-capture system records it -- for identifying tasks whose
    observation does not determine the state (push: the box's height, tilt and spin), where
    Real2Sim's shooting windows must start from recorded states."""
    contacts: str = "mjx"
    """Collision rules of the simulator (``twinrl.physics.Sim``): ``"mjx"``, stock MJX's, or
    ``"mujoco"``, MuJoCo C's box on a plane (every lower corner touches; MJX keeps the corners
    within 1 mm of the deepest)."""
    solver_iterations: int | None = None
    """Constraint-solver iterations of the simulator (default: the scene's ``<option>``). The
    scenes keep few for speed; identification wants the solve converged (push's 6 leave up to
    8 cm/s of the box's velocity unconverged on 1 % of control steps; 12 converge)."""

    def __post_init__(self):
        if self.observation not in ("task", "state"):
            raise ValueError(f"observation must be 'task' or 'state', got {self.observation!r}")
        if int(self.episode_length) < 1:
            raise ValueError(f"episode_length must be >= 1, got {self.episode_length}")
        if int(self.frame_skip) < 1:
            raise ValueError(f"frame_skip must be >= 1, got {self.frame_skip}")
        check_contacts(self.contacts)
        if self.solver_iterations is not None and int(self.solver_iterations) < 1:
            raise ValueError(f"solver_iterations must be >= 1, got {self.solver_iterations}")


def replace_config(config: TaskConfig, **overrides) -> TaskConfig:
    """``dataclasses.replace`` that names an unknown override and the allowed ones."""
    allowed = {f.name for f in dataclasses.fields(config)}
    unknown = sorted(set(overrides) - allowed)
    if unknown:
        raise TypeError(f"unknown config field(s) {', '.join(unknown)} for "
                        f"{type(config).__name__}; allowed: {', '.join(sorted(allowed))}")
    return dataclasses.replace(config, **overrides)


@dataclasses.dataclass(frozen=True)
class PerturbationSpec:
    """How a task's real twin may differ from its simulator: the *distribution* a hidden
    ``twinrl.real.perturbation.Perturbation`` is drawn from. Ranges are (low, high); scale factors
    are drawn log-uniformly per element, additive extras uniformly."""

    mass_scale: tuple[float, float] = (0.85, 1.2)
    """Per-body mass factor (rotational inertia scales with it)."""
    damping_scale: tuple[float, float] = (0.7, 1.5)
    """Per-dof joint damping factor."""
    friction_scale: tuple[float, float] = (0.8, 1.25)
    """Per-geom sliding friction factor."""
    gain_scale: tuple[float, float] = (0.85, 1.1)
    """Per-actuator gain factor (motor constant)."""
    extra_damping: tuple[tuple[str, float, float], ...] = ()
    """``(joint name, low, high)``: damping added to that joint (N s/m or N m s/rad)."""
    extra_frictionloss: tuple[tuple[str, float, float], ...] = ()
    """``(joint name, low, high)``: dry friction added to that joint; an *unmodeled* effect when the
    simulator's MJCF has none (MJX then has no friction-loss row for it at all)."""
    latency_steps: tuple[int, ...] = (0, 1)
    """Action latency in control steps, drawn uniformly from these choices."""
    obs_noise_std: tuple[float, float] = (0.0, 0.01)
    """Standard deviation of Gaussian observation noise, drawn uniformly from this range."""
    camera_pos_std: float = 0.02
    """Standard deviation (m) of each axis of the cameras' true position offset."""
    camera_rot_std: float = 0.03
    """Standard deviation (rad) of each component of the cameras' true rotation offset
    (axis-angle, in the camera frame)."""
    tool_pos_std: float = 0.0
    """Standard deviation (m) of each axis of the grasp offset: where the tool (body ``tool``, the
    arm tasks' peg, spatula or thread) truly sits in the hand, from its nominal place."""
    tool_rot_std: float = 0.0
    """Standard deviation (rad) of each component of the tool's true rotation in the hand
    (axis-angle, in the tool's frame)."""


def tolerance(x: jax.Array, margin: float, value_at_margin: float = 0.1,
              axis: int | None = None) -> jax.Array:
    """Smooth bump in (0, 1]: 1 at ``x = 0``, ``value_at_margin`` at ``|x| = margin`` (Gaussian).

    The Gaussian case of dm_control's ``rewards.tolerance`` with ``bounds=(0, 0)``, chosen because
    it is smooth everywhere, so its gradient never vanishes on a plateau or jumps at a bound.
    With ``axis``, ``|x|`` is the Euclidean norm along that axis (taken squared, so the gradient
    at ``x = 0`` is finite, unlike that of ``jnp.linalg.norm``).
    """
    scale = np.sqrt(-2.0 * np.log(value_at_margin)) / margin
    sq = jnp.square(x) if axis is None else jnp.sum(jnp.square(x), axis=axis)
    return jnp.exp(-0.5 * sq * scale**2)


def small_control(action: jax.Array) -> jax.Array:
    """dm_control's smooth control term: ``(4 + 1 - mean(a^2)) / 5``, in [0.8, 1] for a in [-1, 1].

    Multiplied into a reward it costs effort without ever zeroing the reward."""
    return (5.0 - jnp.mean(jnp.square(jnp.clip(action, -1.0, 1.0)))) / 5.0


class Env(brax_base.Env):
    """A task on a ``Sim``: Brax-compatible, jit/vmap/grad-able.

    Subclasses set ``scene``, ``cameras``, ``reward_term_names``, ``perturbation_spec`` and implement ``initial_state``,
    ``observe`` and ``reward_terms`` (and ``combine`` if the terms are not simply multiplied).

    Args:
      config: the task's config (default: ``default_config()``).
      params: physical parameters the simulator runs with (default: the MJCF's nominal values);
        pass identified ones after Real2Sim, or randomised ones for domain randomisation.
    """

    scene: ClassVar[str]
    """Scene name: a bundled scene (``twinrl/physics/scenes/<scene>.xml``) unless ``mjcf`` says
    otherwise."""
    cameras: ClassVar[tuple[str, ...]]
    """Named cameras of the scene, first one the default view."""
    reward_term_names: ClassVar[tuple[str, ...]]
    """Names of the reward terms, logged as ``metrics['reward/<name>']``."""
    perturbation_spec: ClassVar[PerturbationSpec] = PerturbationSpec()
    """How the real twin of this task differs (the default ``Perturbation`` is drawn from it)."""
    Config: ClassVar[type[TaskConfig]] = TaskConfig

    def __init__(self, config: TaskConfig | None = None, params: PhysParams | None = None,
                 name: str | None = None):
        config = self.default_config() if config is None else config
        if not isinstance(config, self.Config):
            raise TypeError(f"config must be a {self.Config.__name__}, got {type(config).__name__}")
        self.config = config
        self.name = name or type(self).__name__
        sim = Sim.load(self.mjcf(), frame_skip=int(config.frame_skip), name=self.scene,
                       contacts=config.contacts, iterations=config.solver_iterations)
        if params is not None:
            if not isinstance(params, PhysParams):
                raise TypeError(f"params must be a PhysParams, got {type(params).__name__}")
            # Caught here, by name, rather than as an IndexError deep inside a jitted step.
            params.check_shapes(sim.mj_model, f"task {self.name!r} (scene {self.scene!r})")
        self.sim = _with_friction_rows(sim, params)
        self.params = params
        self._sys = None
        r = self.sim.ctrl_range
        if not np.all(np.isfinite(r)):
            raise ValueError(f"scene {self.scene!r}: every actuator needs a ctrlrange, got {r}")
        self._ctrl_lo = jnp.asarray(r[:, 0], jnp.float32)
        self._ctrl_hi = jnp.asarray(r[:, 1], jnp.float32)
        if config.observation == "state":  # instance attributes shadow the task's hooks
            self.observe, self.state_from_obs = self._full_state, self._split_state

    @property
    def default_camera(self) -> str | int:
        """The camera a task's images come from unless one is named: its first camera, else
        its MJCF's first (by name, else id 0), else -1, MuJoCo's free camera (where its viewer
        opens): a user's MJCF without a camera is drawn too."""
        if self.cameras:
            return self.cameras[0]
        m = self.sim.mj_model
        return (m.camera(0).name or 0) if m.ncam else -1

    @property
    def observes_state(self) -> bool:
        """Whether ``state_from_obs`` inverts the observation, so that Real2Sim's shooting
        windows can start from recorded observations (push's task observation cannot: its
        box's height, tilt and spin are not in it; ``observation="state"`` always can)."""
        try:
            self.state_from_obs(jnp.zeros(self.observation_size, jnp.float32))
        except NotImplementedError:
            return False
        return True

    def _full_state(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        return jnp.concatenate([qpos, qvel], axis=-1).astype(jnp.float32)

    def _split_state(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        return obs[..., :self.sim.nq], obs[..., self.sim.nq:]

    @classmethod
    def default_config(cls) -> TaskConfig:
        return cls.Config()

    @classmethod
    def mjcf(cls) -> str:
        """The task's MJCF, as ``twinrl.physics.load_mjcf`` takes it (a bundled scene's name, a
        path or an XML string): the simulator and the real twin are both built from it."""
        return cls.scene

    @property
    def sys(self):
        """The ``twinrl.envs.system.System`` this task was built from (``envs.make(name,
        system=...)``), else None. Brax's domain randomisation sets it to a (traced) randomised
        system inside its vmap; setting it sets ``params``, what ``step`` simulates with."""
        return self._sys

    @sys.setter
    def sys(self, value) -> None:
        self._sys = value
        if value is not None:
            self.params = value.params

    def with_system(self, system) -> "Env":
        """A copy of this task that simulates ``system`` (a ``twinrl.envs.system.System``): its
        ``sys`` and ``params`` are the system's; this task is untouched. The system's action
        latency is the ``LatencyWrapper``'s (``envs.make``, ``LatencyWrapper.with_system``), not
        the task's. Tasks that take more from a system extend it (the arm tasks: the camera's
        hand-eye offset, the tool's grasp, the controller's calibration)."""
        out = copy.copy(self)
        for k, v in list(vars(out).items()):  # hooks bound in __init__ (observe): to the copy
            if isinstance(v, types.MethodType) and v.__self__ is self:
                setattr(out, k, types.MethodType(v.__func__, out))
        Env.sys.fset(out, system)
        return out

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r}, config={self.config!r})"

    # ------------------------------------------------------------------ task hooks
    @abc.abstractmethod
    def initial_state(self, rng: jax.Array) -> tuple[jax.Array, jax.Array]:
        """The reset distribution: ``(qpos, qvel)`` drawn with ``rng``."""

    @abc.abstractmethod
    def observe(self, qpos: jax.Array, qvel: jax.Array) -> jax.Array:
        """The observation vector of a state (noise-free; the real twin adds its own noise)."""

    def state_from_obs(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """``(qpos, qvel)`` whose ``observe`` is ``obs``: the inverse of ``observe``.

        Real2Sim's multiple shooting (``twinrl.real2sim.sysid``) starts each simulated window from
        a recorded observation, so it needs this for tasks whose observation determines the state.
        Tasks that cannot invert their observation raise ``NotImplementedError`` saying why.
        """
        raise NotImplementedError(
            f"{type(self).__name__}.state_from_obs: this task does not say how to recover the "
            "physical state (qpos, qvel) from its observation")

    @abc.abstractmethod
    def reward_terms(self, qpos: jax.Array, qvel: jax.Array,
                     action: jax.Array) -> dict[str, jax.Array]:
        """Smooth reward terms, each in [0, 1], of the state reached by ``action`` in [-1, 1]."""

    def combine(self, terms: Mapping[str, jax.Array]) -> jax.Array:
        """The reward from its terms: their product (so per-step reward is in [0, 1])."""
        r = jnp.ones(())
        for k in self.reward_term_names:
            r = r * terms[k]
        return r

    def control(self, qpos: jax.Array, qvel: jax.Array, action: jax.Array) -> jax.Array:
        """The actuators' ``ctrl`` for ``action`` in the state ``(qpos, qvel)``: the task's
        controller, run by the simulator and by the real twin alike (a robot's controller sees its
        measured joints). Default: ``action_to_ctrl`` (state-independent); the arm tasks turn
        end-effector commands into joint targets here (``twinrl.envs.arm.base``)."""
        return self.action_to_ctrl(action)

    def sim_step(self, data: mjx.Data, action: jax.Array, params: PhysParams | None = None
                 ) -> mjx.Data:
        """One control step of the simulator from ``data`` with ``action`` through ``control``
        (``params``: the physical parameters; None: the simulator's own). The step every rollout
        of the task (``step``, trajopt, sysid, the hybrid model) takes."""
        return self.sim.step(data, self.control(data.qpos, data.qvel, action), params)

    def reward(self, qpos, qvel, action) -> tuple[jax.Array, dict[str, jax.Array]]:
        terms = self.reward_terms(qpos, qvel, action)
        return self.combine(terms), terms

    def action_to_ctrl(self, action: jax.Array) -> jax.Array:
        """Map an action in [-1, 1] (clipped) affinely onto the actuators' ``ctrlrange``."""
        a = jnp.clip(action, -1.0, 1.0)
        return self._ctrl_lo + 0.5 * (a + 1.0) * (self._ctrl_hi - self._ctrl_lo)

    # ------------------------------------------------------------------ Brax API
    def reset(self, rng: jax.Array) -> State:
        qpos, qvel = self.initial_state(rng)
        data = self.sim.init(qpos, qvel)
        zero = jnp.zeros(())
        return State(
            pipeline_state=data,
            obs=self.observe(data.qpos, data.qvel),
            reward=zero,
            done=zero,
            metrics={f"reward/{k}": zero for k in self.reward_term_names},
            info={},
        )

    def step(self, state: State, action: jax.Array) -> State:
        # JAX's default float (float32; float64 under x64, for finite-difference checks)
        action = jnp.asarray(action, jnp.result_type(float))
        if action.size != self.action_size:  # shapes are static: caught once, at trace time
            raise ValueError(f"{self.name}: action has shape {tuple(action.shape)}; the task "
                             f"takes ({self.action_size},)")
        action = action.reshape(self.action_size)
        data = self.sim_step(state.pipeline_state, action, self.params)
        reward, terms = self.reward(data.qpos, data.qvel, action)
        # A diverged simulation ends the episode instead of feeding NaN to the learner.
        finite = jnp.all(jnp.isfinite(data.qpos)) & jnp.all(jnp.isfinite(data.qvel))
        done = jnp.where(finite, state.done, 1.0)
        metrics = dict(state.metrics)
        metrics.update({f"reward/{k}": v for k, v in terms.items()})
        return state.replace(pipeline_state=data, obs=self.observe(data.qpos, data.qvel),
                             reward=reward, done=done, metrics=metrics)

    def unroll(self, state: State, actions: jax.Array) -> tuple[State, jax.Array]:
        """Open-loop rollout of ``actions`` (T, action_size) with ``lax.scan``.

        Returns the final state and the (T,) rewards; ``jax.grad`` of ``rewards.sum()`` w.r.t.
        ``actions`` is the first-order policy gradient of PODS/SHAC.
        """
        def body(s, a):
            s = self.step(s, a)
            return s, s.reward
        return jax.lax.scan(body, state, actions)

    @property
    def observation_size(self) -> int:
        shape = jax.eval_shape(self.reset, jax.ShapeDtypeStruct((2,), jnp.uint32)).obs.shape
        return int(shape[-1])

    @property
    def action_size(self) -> int:
        return self.sim.nu

    @property
    def backend(self) -> str:
        return "mjx"

    @property
    def dt(self) -> float:
        """Control period in seconds."""
        return self.sim.dt

    @property
    def episode_length(self) -> int:
        return int(self.config.episode_length)



def _with_friction_rows(sim: Sim, params: PhysParams | None) -> Sim:
    """``sim``, recompiled so that every dof given a friction loss by ``params`` has one.

    MJX decides at ``mjx.put_model`` which dofs get a friction-loss constraint row (those whose
    compiled ``dof_frictionloss`` is non-zero); a dof without a row ignores any friction loss that
    ``PhysParams.apply`` writes later. Identified (or true) parameters that add dry friction where
    the MJCF has none (the cartpole's rail) must therefore reach the compiled model. Traced
    parameters (vmapped domain randomisation) keep the rows the MJCF has.
    """
    if params is None or isinstance(params.frictionloss, jax.core.Tracer):
        return sim
    fl = np.asarray(params.frictionloss, np.float64)
    need = (fl > 0) & (sim.mj_model.dof_frictionloss == 0)
    if not need.any():
        return sim
    mj = copy.deepcopy(sim.mj_model)
    mj.dof_frictionloss[need] = fl[need]
    return sim.recompiled(mj)
