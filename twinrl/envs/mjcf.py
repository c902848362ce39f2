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

Learning in it (Learn@Sim on your MJCF) needs a reward: ``from_mjcf(path, reward=fn)`` with
``fn(qpos, qvel, action)`` written in ``jax.numpy`` (the state the step reached, the action in
[-1, 1]) returning the step's reward, or a dict of named terms (summed; each logged as
``metrics["reward/<name>"]``), and ``reset_noise`` to start episodes off ``qpos0`` (uniform in
+-``reset_noise`` on every qpos and qvel entry, quaternions renormalised, as Gymnasium's MuJoCo
tasks do). Every trainer takes the task as it takes a registered one, analytic gradients
included (the reward's own gradient is part of them):

    def upright(qpos, qvel, action):
        return {"up": jnp.cos(qpos[0]), "effort": -0.01 * jnp.sum(action ** 2)}
    env = envs.from_mjcf("my_pendulum.xml", reward=upright, reset_noise=0.1, episode_length=200)
    policy, params, metrics = twinrl.learn.shac.train(env, SHACConfig(epochs=50))

From the shell, ``twinrl train --env my_pendulum.xml --reward rewards.py:upright --algo pods``
does the same (``load_reward`` reads the spec; ``task_spec`` / ``from_spec`` keep the file and
the reward in the checkpoint so ``twinrl eval`` rebuilds the task), and ``real.make_real(env)``
is a MuJoCo C twin of it with a hidden perturbation.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.envs.base import Env, TaskConfig, replace_config

__all__ = ["MJCFTask", "MJCFConfig", "from_mjcf", "save_mjcf", "read_log", "load_reward",
           "from_spec", "task_spec"]


@dataclasses.dataclass(frozen=True)
class MJCFConfig(TaskConfig):
    episode_length: int = 1000
    frame_skip: int = 1
    observation: str = "state"
    """Always the full state (``from_mjcf`` refuses ``"task"``: a user's MJCF has no task
    observation)."""


class MJCFTask(Env):
    """A user's MJCF (``from_mjcf``): observation ``[qpos, qvel]``, actions onto the
    actuators' control ranges, reset at ``qpos0`` (or the MJCF's first keyframe), at rest unless
    ``reset_noise``; the reward ``from_mjcf``'s ``reward`` gives (0 every step without one)."""

    Config = MJCFConfig
    cameras = ()
    reward_term_names = ()
    source: str = ""
    """The MJCF (a path or an XML string) this task's class was made for."""
    reward_fn = None
    """``from_mjcf``'s ``reward`` (None: no reward)."""
    reward_is_dict: bool = False
    reset_noise: float = 0.0

    @classmethod
    def mjcf(cls) -> str:
        return cls.source

    def initial_state(self, rng):
        m = self.sim.mj_model
        qpos = m.key_qpos[0] if m.nkey else m.qpos0
        qvel = m.key_qvel[0] if m.nkey else np.zeros(m.nv)
        dt = jnp.result_type(float)
        qpos, qvel = jnp.asarray(qpos, dt), jnp.asarray(qvel, dt)
        if not self.reset_noise:
            return qpos, qvel
        kp, kv = jax.random.split(rng)
        u = float(self.reset_noise)
        qpos = qpos + jax.random.uniform(kp, qpos.shape, dt, -u, u)
        qvel = qvel + jax.random.uniform(kv, qvel.shape, dt, -u, u)
        for a in _quaternion_addresses(m):
            q = qpos[a:a + 4]
            qpos = qpos.at[a:a + 4].set(q / jnp.linalg.norm(q))
        return qpos, qvel

    # observation="state" (MJCFConfig's only value): Env.__init__ makes the full state the
    # observation and state_from_obs its split; Env wants the hook defined all the same
    observe = Env._full_state

    def reward_terms(self, qpos, qvel, action):
        if self.reward_fn is None:
            return {}
        r = self.reward_fn(qpos, qvel, action)
        if self.reward_is_dict:
            return {k: jnp.asarray(v) for k, v in r.items()}
        return {"reward": jnp.asarray(r)}

    def combine(self, terms):
        total = jnp.zeros(())
        for k in self.reward_term_names:
            total = total + terms[k]
        return total

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


def read_log(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(qpos, qvel, ctrl)`` of a robot's log, an ``.npz`` holding those three arrays (shapes:
    ``MJCFTask.transitions``). Raises ``ValueError`` naming what is wrong: an array missing (and
    those it has), or a file that is no readable ``.npz``."""
    try:
        with np.load(path) as z:
            names = z.files
            arrays = {k: z[k] for k in ("qpos", "qvel", "ctrl") if k in names}
    except (OSError, ValueError) as e:  # not an .npz, a pickled object array, ...
        raise ValueError(f"not a readable .npz ({e})") from None
    missing = [k for k in ("qpos", "qvel", "ctrl") if k not in arrays]
    if missing:
        raise ValueError(f"no {', '.join(missing)} array (it has {', '.join(names) or 'none'})")
    return arrays["qpos"], arrays["qvel"], arrays["ctrl"]


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


def from_mjcf(mjcf, *, name: str | None = None, reward=None, reset_noise: float = 0.0,
              **config) -> MJCFTask:
    """The task of an MJCF (a path or an XML string; module docstring). ``reward``:
    ``fn(qpos, qvel, action)`` -> a scalar or a dict of scalar terms (summed), in
    ``jax.numpy``; ``reset_noise``: the half-width of the uniform noise added to every qpos and
    qvel entry at reset. ``config``: ``MJCFConfig`` fields (``frame_skip`` physics steps per
    logged sample, default 1; ``episode_length``; ``solver_iterations``; ``contacts``)."""
    text = str(mjcf)
    is_xml = text.lstrip().startswith("<")
    stem = name or ("mjcf" if is_xml else Path(text).stem)
    if config.get("observation", "state") != "state":
        raise ValueError("a user's MJCF task observes the full state; observation='task' is "
                         "for the registered tasks")
    if reward is not None and not callable(reward):
        raise TypeError(f"reward must be a function (qpos, qvel, action) -> reward, got "
                        f"{type(reward).__name__}")
    noise = float(reset_noise)
    if not np.isfinite(noise) or noise < 0:
        raise ValueError(f"reset_noise must be a finite half-width >= 0, got {reset_noise!r}")
    cfg = replace_config(MJCFConfig(), **config)
    attrs = {"scene": stem, "source": text if is_xml else str(Path(text)),
             "reward_fn": staticmethod(reward) if reward is not None else None,
             "reset_noise": noise}
    cls = type(f"MJCFTask[{stem}]", (MJCFTask,), attrs)
    env = cls(cfg, name=stem)
    if reward is not None:
        cls.reward_is_dict, cls.reward_term_names = _reward_terms(env, reward)
    return env


def _reward_terms(env: MJCFTask, reward) -> tuple[bool, tuple[str, ...]]:
    """Whether ``reward`` returns a dict, and its term names; traced once (``jax.eval_shape``)
    on the reset state, so a reward that does not return a scalar (or a dict of scalars) is
    one line here, not a shape error inside a compiled rollout."""
    qpos, qvel = env.initial_state(jax.random.key(0))
    action = jnp.zeros(env.action_size, qpos.dtype)
    try:
        out = jax.eval_shape(reward, qpos, qvel, action)
    except Exception as e:  # the user's function: say where it failed, keep the cause
        raise ValueError(f"{env.name}: reward(qpos, qvel, action) failed on the reset state "
                         f"(qpos ({env.sim.nq},), qvel ({env.sim.nv},), action "
                         f"({env.action_size},)): {_cause(e)}") from e
    terms = out if isinstance(out, dict) else {"reward": out}
    for k, v in terms.items():
        if not hasattr(v, "shape") or v.shape != ():
            shape = getattr(v, "shape", type(v).__name__)
            raise ValueError(f"{env.name}: reward term {k!r} must be a scalar, got shape "
                             f"{shape}")
    return isinstance(out, dict), tuple(str(k) for k in terms)


def _quaternion_addresses(model) -> list[int]:
    """qpos addresses of every free joint's and ball joint's quaternion."""
    import mujoco

    out = []
    for j in range(model.njnt):
        t, a = model.jnt_type[j], int(model.jnt_qposadr[j])
        if t == mujoco.mjtJoint.mjJNT_FREE:
            out.append(a + 3)
        elif t == mujoco.mjtJoint.mjJNT_BALL:
            out.append(a)
    return out


def _cause(e: Exception) -> str:
    """A user function's exception in one line: its type and its message's first line."""
    return f"{type(e).__name__}: {(str(e).splitlines() or [''])[0]}"


def load_reward(spec: str):
    """The function a reward spec names: ``"FILE.py:NAME"`` (a Python file's function) or
    ``"package.module:NAME"`` (an importable module's) -- what ``twinrl train --reward`` takes.
    A bad spec is a one-line ``ValueError`` naming what is missing."""
    import importlib
    import importlib.util

    text = str(spec)
    where, sep, name = text.rpartition(":")
    if not sep or not where or not name.isidentifier():
        raise ValueError(f"reward {text!r}: give FILE.py:FUNCTION or module:FUNCTION")
    if where.endswith(".py"):
        path = Path(where)
        if not path.is_file():
            raise ValueError(f"reward {text!r}: no file {path}")
        mod_spec = importlib.util.spec_from_file_location(f"twinrl_reward_{path.stem}", path)
        module = importlib.util.module_from_spec(mod_spec)
        try:
            mod_spec.loader.exec_module(module)
        except Exception as e:  # the user's file: say which and why, in one line
            raise ValueError(f"reward {text!r}: {path} failed to run: {_cause(e)}") from e
    else:
        try:
            module = importlib.import_module(where)
        except ImportError as e:
            raise ValueError(f"reward {text!r}: cannot import {where}: {e}") from e
    fn = getattr(module, name, None)
    if not callable(fn):
        raise ValueError(f"reward {text!r}: {where} has no function {name}")
    return fn


def from_spec(spec: dict) -> MJCFTask:
    """The task ``spec`` describes, as ``task_spec`` writes it (a checkpoint's ``mjcf``
    entry): the MJCF's path, the reward spec (``load_reward``), ``reset_noise`` and the config
    fields. What ``twinrl eval`` rebuilds a user's MJCF task from."""
    missing = [k for k in ("mjcf", "name") if k not in spec]
    if missing:
        raise ValueError(f"an MJCF task spec needs {', '.join(missing)}")
    reward = load_reward(spec["reward"]) if spec.get("reward") else None
    return from_mjcf(spec["mjcf"], name=spec["name"], reward=reward,
                     reset_noise=float(spec.get("reset_noise", 0.0)),
                     **dict(spec.get("config") or {}))


def task_spec(env: MJCFTask, reward: str | None) -> dict:
    """``from_spec``'s input for ``env`` (an MJCF file's task) built with the reward spec
    ``reward``: the file's absolute path, so a checkpoint rebuilds it from anywhere."""
    if env.source.lstrip().startswith("<"):
        raise ValueError("a task of an XML string has no file to rebuild it from")
    reward_spec = None
    if reward:
        where, _, name = str(reward).rpartition(":")
        reward_spec = (f"{Path(where).resolve()}:{name}" if where.endswith(".py") else
                       str(reward))
    defaults = dataclasses.asdict(MJCFConfig())
    config = {k: v for k, v in dataclasses.asdict(env.config).items() if defaults.get(k) != v}
    return {"mjcf": str(Path(env.source).resolve()), "name": env.name, "reward": reward_spec,
            "reset_noise": float(env.reset_noise), "config": config}
