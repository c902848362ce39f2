"""Your robot's MJCF as a task, so Real2Sim and the gradients work on it (``from_mjcf``).

The registered tasks (``twinrl.envs.make``) carry rewards, reset distributions and real twins.
Identifying *your* robot needs none of that: a simulator of your MJCF whose observation is the
full state a logger records (``[qpos, qvel]``) and whose action is what you sent the actuators.
``from_mjcf(path)`` builds that task, an ``Env`` like the others (jit/vmap/grad-able, Brax's
``reset``/``step``), so ``twinrl.real2sim.sysid.fit(env, data)`` identifies masses, damping,
friction loss, actuator gains and the action latency from your logs, and ``twinrl gradcheck``
checks its gradients. Actions are ``Env``'s: [-1, 1] mapped onto each actuator's
``ctrlrange`` (which every actuator must have); ``transitions(qpos, qvel, ctrl)`` turns logged
states and controls in the actuators' own units into the ``{"obs", "action", "next_obs"}``
arrays ``sysid.fit`` takes.

    env = envs.from_mjcf("my_arm.xml", frame_skip=1)     # one log sample per physics step
    data = env.transitions(qpos, qvel, ctrl)   # (E, T + 1, nq), (E, T + 1, nv), (E, T, nu)
    result = sysid.fit(env, data, sysid.SysidConfig(known=(("mass/base", 2.0),)))
    envs.mjcf.save_mjcf(env, result.params, "my_arm_identified.xml")   # for MuJoCo C, MJX, ...

The log must be sampled at the control period ``dt * frame_skip`` of the MJCF's timestep, and
the simulator runs MJX (``twinrl.physics.Sim``): a model MJX cannot simulate is refused at
``from_mjcf`` with one line naming what it lacks.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from twinrl.envs.base import Env, TaskConfig, replace_config

__all__ = ["MJCFTask", "MJCFConfig", "from_mjcf", "save_mjcf"]


@dataclasses.dataclass(frozen=True)
class MJCFConfig(TaskConfig):
    episode_length: int = 1000
    frame_skip: int = 1
    observation: str = "state"
    """Always the full state (``from_mjcf`` refuses ``"task"``: a user's MJCF has no task
    observation)."""


class MJCFTask(Env):
    """A user's MJCF (``from_mjcf``): observation ``[qpos, qvel]``, actions onto the
    actuators' control ranges, reset at ``qpos0`` (or the MJCF's first keyframe) at rest, no
    reward (every step's is 0)."""

    Config = MJCFConfig
    cameras = ()
    reward_term_names = ()
    source: str = ""
    """The MJCF (a path or an XML string) this task's class was made for."""

    @classmethod
    def mjcf(cls) -> str:
        return cls.source

    def initial_state(self, rng):
        m = self.sim.mj_model
        qpos = m.key_qpos[0] if m.nkey else m.qpos0
        qvel = m.key_qvel[0] if m.nkey else np.zeros(m.nv)
        dt = jnp.result_type(float)
        return jnp.asarray(qpos, dt), jnp.asarray(qvel, dt)

    # observation="state" (MJCFConfig's only value): Env.__init__ makes the full state the
    # observation and state_from_obs its split; Env wants the hook defined all the same
    observe = Env._full_state

    def reward_terms(self, qpos, qvel, action):
        return {}

    def combine(self, terms):
        return jnp.zeros(())

    def ctrl_to_action(self, ctrl) -> np.ndarray:
        """Controls in the actuators' units -> actions in [-1, 1] (``action_to_ctrl``'s
        inverse); a control outside its ``ctrlrange`` is a ``ValueError`` naming it (the
        simulator would clip it, so the fit would see another input than the robot had)."""
        ctrl = np.asarray(ctrl, np.float64)
        lo, hi = (np.asarray(x, np.float64) for x in (self._ctrl_lo, self._ctrl_hi))
        if ctrl.shape[-1:] != lo.shape:
            raise ValueError(f"ctrl has {ctrl.shape[-1] if ctrl.ndim else 0} columns; "
                             f"{self.name} has {lo.size} actuators")
        tol = 1e-6 * np.maximum(1.0, hi - lo)
        out = (ctrl < lo - tol) | (ctrl > hi + tol)
        if out.any():
            idx = tuple(int(i) for i in np.argwhere(out)[0])
            j = idx[-1]
            raise ValueError(f"ctrl{list(idx)} = {ctrl[idx]:g} is outside actuator {j}'s "
                             f"ctrlrange [{lo[j]:g}, {hi[j]:g}]")
        return (2.0 * (ctrl - lo) / np.where(hi > lo, hi - lo, 1.0) - 1.0).astype(np.float32)

    def transitions(self, qpos, qvel, ctrl) -> dict[str, np.ndarray]:
        """Logged states ``qpos`` (E, T + 1, nq) and ``qvel`` (E, T + 1, nv) and the controls
        sent between them ``ctrl`` (E, T, nu) (or one episode without the leading axis) ->
        ``{"obs", "action", "next_obs"}`` for ``twinrl.real2sim.sysid.fit``."""
        qpos, qvel, ctrl = (np.asarray(x, np.float64) for x in (qpos, qvel, ctrl))
        if qpos.ndim == 2:
            qpos, qvel, ctrl = qpos[None], qvel[None], ctrl[None]
        nq, nv = self.sim.nq, self.sim.nv
        if qpos.ndim != 3 or qpos.shape[-1] != nq or qvel.shape[:2] != qpos.shape[:2] \
                or qvel.shape[-1] != nv:
            raise ValueError(f"qpos {qpos.shape} and qvel {qvel.shape} must be (E, T + 1, {nq}) "
                             f"and (E, T + 1, {nv})")
        if ctrl.shape[:2] != (qpos.shape[0], qpos.shape[1] - 1):
            raise ValueError(f"ctrl {ctrl.shape} must be (E, T, nu) with T = {qpos.shape[1] - 1}"
                             f" (one control between each two logged states)")
        obs = np.concatenate([qpos, qvel], axis=-1).astype(np.float32)
        return {"obs": obs[:, :-1], "action": self.ctrl_to_action(ctrl), "next_obs": obs[:, 1:]}


def save_mjcf(env: MJCFTask, params, path) -> Path:
    """Your MJCF with ``params`` (``PhysParams``, e.g. ``sysid.fit(...).params``) written in,
    saved at ``path`` (MuJoCo's own writer, ``mj_saveLastXML``: the file compiles to the same
    model, every value to the 6 significant digits MuJoCo writes; a body whose mass changed gets
    an explicit ``<inertial>``)."""
    import mujoco

    from twinrl.physics import mujoco_warnings

    path = Path(path)
    src = env.mjcf()
    # mj_saveLastXML writes the model MuJoCo parsed last: parse this one right before
    with mujoco_warnings(env.name):
        model = (mujoco.MjModel.from_xml_string(src) if src.lstrip().startswith("<")
                 else mujoco.MjModel.from_xml_path(src))
    model = params.to_mjmodel(model)
    path.parent.mkdir(parents=True, exist_ok=True)
    mujoco.mj_saveLastXML(str(path), model)
    return path


def from_mjcf(mjcf, *, name: str | None = None, **config) -> MJCFTask:
    """The task of an MJCF (a path or an XML string; module docstring). ``config``:
    ``MJCFConfig`` fields (``frame_skip`` physics steps per logged sample, default 1;
    ``episode_length``; ``solver_iterations``; ``contacts``)."""
    text = str(mjcf)
    is_xml = text.lstrip().startswith("<")
    stem = name or ("mjcf" if is_xml else Path(text).stem)
    if config.get("observation", "state") != "state":
        raise ValueError("a user's MJCF task observes the full state; observation='task' is "
                         "for the registered tasks")
    cfg = replace_config(MJCFConfig(), **config)
    cls = type(f"MJCFTask[{stem}]", (MJCFTask,), {"scene": stem, "source": text if is_xml
                                                  else str(Path(text))})
    return cls(cfg, name=stem)

