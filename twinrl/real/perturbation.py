"""``Perturbation``: the hidden difference between a task's simulator and its real twin.

The real twin (``twinrl.real.twin``) stands in for a physical robot, so it must differ from the
simulator the way a robot differs from its model: wrong masses, damping, friction and motor
constants (what Real2Sim's ``sysid`` identifies), effects the simulator does not model at all
(rail friction on the cartpole, as in the Hybrid Differentiable Simulation study), action latency,
sensor noise, and a camera mounted slightly off its nominal pose (what ``real2sim.visual`` fits).
One ``Perturbation`` is a concrete draw of all of these; each task's ``PerturbationSpec``
(``twinrl.envs.base``) is the distribution it is drawn from.

A perturbation is hidden from learning: the real twin applies it and reveals it only through
``RealTwin.oracle()``, for evaluation (tests grep the package so nothing else calls it).
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from twinrl.envs.base import Env, PerturbationSpec
from twinrl.physics.params import position_servos

__all__ = ["Perturbation", "rotvec_quat"]

_SCALES = ("mass_scale", "damping_scale", "friction_scale", "gain_scale")
_EXTRAS = ("extra_damping", "extra_frictionloss")


@dataclasses.dataclass(frozen=True)
class Perturbation:
    """A concrete real-twin perturbation. Empty tuples mean "unchanged" (factor 1, extra 0)."""

    mass_scale: tuple[float, ...] = ()
    """Factor per body except the world body (nbody-1,); rotational inertia scales with it."""
    damping_scale: tuple[float, ...] = ()
    """Factor on joint damping per dof (nv,)."""
    friction_scale: tuple[float, ...] = ()
    """Factor on sliding friction per geom (ngeom,)."""
    gain_scale: tuple[float, ...] = ()
    """Factor on actuator gain per actuator (nu,)."""
    extra_damping: tuple[float, ...] = ()
    """Damping added per dof (nv,), after scaling."""
    extra_frictionloss: tuple[float, ...] = ()
    """Dry friction added per dof (nv,): unmodeled where the simulator's MJCF has none."""
    actuator_offset: tuple[float, ...] = ()
    """Constant offset per actuator, in control units: the force is ``gain * (ctrl + offset)``, as
    from a motor driver's zero error. The simulator's ``PhysParams`` have no such term, so it is an
    effect sysid cannot model (only the hybrid model and the residual policy can correct it). Never
    drawn by ``sample``: set it explicitly (``dataclasses.replace``) for such a benchmark twin."""
    latency_steps: int = 0
    """Control steps between an action being sent and being applied (zeros before the first)."""
    obs_noise_std: float = 0.0
    """Standard deviation of the Gaussian noise added to every observation component."""
    camera_pos_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Offset (m) of every camera's true position from its nominal one, in its parent frame."""
    camera_rot_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Rotation (axis-angle, rad, camera frame) of every camera's true orientation from nominal."""
    tool_pos_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Grasp offset (m): the true position of body ``tool`` in its parent (the hand) minus the
    nominal one. Only for scenes with a body named ``tool`` (the arm tasks)."""
    tool_rot_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Grasp rotation (axis-angle, rad, in the tool's frame) of body ``tool`` from nominal."""

    def __post_init__(self):
        for name in _SCALES + _EXTRAS:
            v = np.asarray(getattr(self, name), dtype=np.float64)
            bad = ~np.isfinite(v) | ((v <= 0) if name in _SCALES else (v < 0))
            if v.ndim != 1 or bad.any():
                where = int(np.flatnonzero(bad)[0]) if v.ndim == 1 else 0
                raise ValueError(
                    f"Perturbation.{name} must be a flat tuple of "
                    f"{'positive' if name in _SCALES else 'non-negative'} finite "
                    f"numbers; got {getattr(self, name)!r} (index {where})"
                )
            object.__setattr__(self, name, tuple(float(x) for x in v))
        offset = np.asarray(self.actuator_offset, dtype=np.float64)
        if offset.ndim != 1 or not np.all(np.isfinite(offset)):
            raise ValueError(f"Perturbation.actuator_offset must be a flat tuple of finite numbers, "
                             f"got {self.actuator_offset!r}")
        object.__setattr__(self, "actuator_offset", tuple(float(x) for x in offset))
        if int(self.latency_steps) != self.latency_steps or self.latency_steps < 0:
            raise ValueError(
                f"Perturbation.latency_steps must be an integer >= 0, got {self.latency_steps!r}"
            )
        object.__setattr__(self, "latency_steps", int(self.latency_steps))
        if not (math.isfinite(self.obs_noise_std) and self.obs_noise_std >= 0):
            raise ValueError(
                f"Perturbation.obs_noise_std must be finite and >= 0, got {self.obs_noise_std!r}"
            )
        for name in ("camera_pos_offset", "camera_rot_offset", "tool_pos_offset",
                     "tool_rot_offset"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(
                    f"Perturbation.{name} must be 3 finite numbers, got {getattr(self, name)!r}"
                )
            object.__setattr__(self, name, tuple(float(x) for x in v))

    # ------------------------------------------------------------------ construction
    @classmethod
    def none(cls) -> "Perturbation":
        """No perturbation: the real twin's physics is the simulator's (up to the engines)."""
        return cls()

    @classmethod
    def from_params(cls, model: mujoco.MjModel, params, *, latency_steps: int = 0,
                    obs_noise_std: float = 0.0) -> "Perturbation":
        """The perturbation that turns ``model`` (the task's nominal ``mujoco.MjModel``) into
        one with ``params`` (a ``PhysParams``, e.g. a sysid fit's): a real twin made with it
        simulates the *identified* model in MuJoCo C, with that latency and sensor noise -- data
        simulated from what was learned, for indirect inference (``sysid.indirect``). Masses,
        damping, sliding friction and gains become scales; damping where the model has none
        becomes ``extra_damping``, a friction loss above the model's ``extra_frictionloss``.
        ``ValueError`` naming the field when ``params`` differ from ``model`` where a
        perturbation cannot say so (armature, actuator bias, gravity, a friction loss below the
        model's, a mass, friction or gain that is 0 in the model and not in ``params``)."""
        p = {k: np.asarray(v, np.float64) for k, v in params.as_dict().items()}
        fixed = {"armature": model.dof_armature, "bias": model.actuator_biasprm[:, :3],
                 "gravity": model.opt.gravity}
        for name, value in fixed.items():
            if p[name].shape != np.shape(value) or not np.allclose(p[name], value, rtol=1e-6,
                                                                   atol=1e-9):
                raise ValueError(f"Perturbation.from_params: params.{name} differ from the "
                                 f"model's, and a perturbation has no {name}")
        extra = p["frictionloss"] - model.dof_frictionloss
        if np.any(extra < -1e-9):
            raise ValueError("Perturbation.from_params: params.frictionloss below the model's "
                             "(a perturbation only adds friction loss)")

        def ratio(name, value, nominal):
            nominal = np.asarray(nominal, np.float64)
            if name != "damping" and np.any((nominal == 0) & (np.abs(value) > 1e-12)):
                raise ValueError(f"Perturbation.from_params: params.{name} is not 0 where the "
                                 f"model's is, and a scale of 0 stays 0")
            safe = np.where(nominal != 0, nominal, 1.0)
            return tuple(np.where(nominal != 0, value / safe, 1.0).tolist())

        dof_damping = np.asarray(model.dof_damping, np.float64)
        return cls(mass_scale=ratio("mass", p["mass"], model.body_mass[1:]),
                   damping_scale=ratio("damping", p["damping"], dof_damping),
                   extra_damping=tuple(np.where(dof_damping == 0, np.maximum(p["damping"], 0.0),
                                                0.0).tolist()),
                   friction_scale=ratio("friction", p["friction"], model.geom_friction[:, 0]),
                   gain_scale=ratio("gain", p["gain"], model.actuator_gainprm[:, 0]),
                   extra_frictionloss=tuple(np.maximum(extra, 0.0).tolist()),
                   latency_steps=int(latency_steps), obs_noise_std=float(obs_noise_std))

    @classmethod
    def sample(cls, task: str | Env, rng: int | np.random.Generator) -> "Perturbation":
        """A draw from the task's ``perturbation_spec`` (the default real twin of that task).

        Args:
          task: a registered task name or an ``Env``.
          rng: a seed or a ``numpy.random.Generator``; the same seed gives the same draw.
        """
        if isinstance(task, str):
            from twinrl.envs import make

            task = make(task)
        if not isinstance(task, Env):
            raise TypeError(f"task must be a task name or a twinrl.envs.Env, got {task!r}")
        rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        spec: PerturbationSpec = task.perturbation_spec
        m = task.sim.mj_model

        def log_uniform(lo_hi, n):
            lo, hi = lo_hi
            if not 0 < lo <= hi:
                raise ValueError(
                    f"{type(task).__name__}.perturbation_spec: scale range must "
                    f"satisfy 0 < low <= high, got {lo_hi}"
                )
            return tuple(np.exp(rng.uniform(np.log(lo), np.log(hi), size=n)))

        def per_joint(items, what):
            out = np.zeros(m.nv)
            for joint, lo, hi in items:
                jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, joint)
                if jid < 0:
                    raise ValueError(
                        f"{type(task).__name__}.perturbation_spec.{what}: scene "
                        f"{task.scene!r} has no joint {joint!r}"
                    )
                out[m.jnt_dofadr[jid]] += rng.uniform(lo, hi)
            return tuple(out)

        return cls(
            mass_scale=log_uniform(spec.mass_scale, m.nbody - 1),
            damping_scale=log_uniform(spec.damping_scale, m.nv),
            friction_scale=log_uniform(spec.friction_scale, m.ngeom),
            gain_scale=log_uniform(spec.gain_scale, m.nu),
            extra_damping=per_joint(spec.extra_damping, "extra_damping"),
            extra_frictionloss=per_joint(spec.extra_frictionloss, "extra_frictionloss"),
            latency_steps=int(rng.choice(np.asarray(spec.latency_steps))),
            obs_noise_std=float(rng.uniform(*spec.obs_noise_std)),
            camera_pos_offset=tuple(rng.normal(0.0, spec.camera_pos_std, size=3)),
            camera_rot_offset=tuple(rng.normal(0.0, spec.camera_rot_std, size=3)),
            **cls._tool_offsets(spec, m, rng),
        )

    @staticmethod
    def _tool_offsets(spec: PerturbationSpec, m: mujoco.MjModel, rng) -> dict:
        # Drawn only where the spec asks for them, so older tasks' draws stay what they were.
        if not (spec.tool_pos_std or spec.tool_rot_std):
            return {}
        if mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "tool") < 0:
            raise ValueError("perturbation_spec.tool_pos_std/tool_rot_std: the scene has no body "
                             "named 'tool'")
        return {"tool_pos_offset": tuple(rng.normal(0.0, spec.tool_pos_std, size=3)),
                "tool_rot_offset": tuple(rng.normal(0.0, spec.tool_rot_std, size=3))}

    def is_none(self) -> bool:
        """True when applying this perturbation changes nothing."""
        return (
            all(x == 1.0 for k in _SCALES for x in getattr(self, k))
            and all(x == 0.0 for k in _EXTRAS for x in getattr(self, k))
            and not any(self.actuator_offset)
            and self.latency_steps == 0
            and self.obs_noise_std == 0.0
            and not any(self.camera_pos_offset)
            and not any(self.camera_rot_offset)
            and not any(self.tool_pos_offset)
            and not any(self.tool_rot_offset)
        )

    # ------------------------------------------------------------------ application
    def apply(self, model: mujoco.MjModel) -> None:
        """Write this perturbation into ``model`` (a ``mujoco.MjModel``, modified in place)."""

        def vec(name, n, default):
            v = getattr(self, name)
            if not v:
                return np.full(n, default)
            if len(v) != n:
                raise ValueError(f"Perturbation.{name} has {len(v)} entries; this model needs {n}")
            return np.asarray(v)

        ms = vec("mass_scale", model.nbody - 1, 1.0)
        model.body_mass[1:] *= ms
        model.body_inertia[1:] *= ms[:, None]
        model.dof_damping[:] = model.dof_damping * vec("damping_scale", model.nv, 1.0) + vec(
            "extra_damping", model.nv, 0.0
        )
        model.dof_frictionloss[:] += vec("extra_frictionloss", model.nv, 0.0)
        model.geom_friction[:, 0] *= vec("friction_scale", model.ngeom, 1.0)
        gs = vec("gain_scale", model.nu, 1.0)
        # A position servo (force = kp ctrl - kp q - kv qdot) has its stiffness in the gain and in
        # the bias; a "gain" error of such a controller scales both, else it would also move the
        # servo's set point.
        servo = position_servos(model)
        model.actuator_gainprm[:, 0] *= gs
        model.actuator_biasprm[servo, 1] *= gs[servo]
        offset = vec("actuator_offset", model.nu, 0.0)
        for i in np.flatnonzero(offset):
            if int(model.actuator_gaintype[i]) != int(mujoco.mjtGain.mjGAIN_FIXED) or (
                    int(model.actuator_biastype[i]) not in (int(mujoco.mjtBias.mjBIAS_NONE),
                                                            int(mujoco.mjtBias.mjBIAS_AFFINE))):
                raise ValueError(f"Perturbation.actuator_offset: actuator {i} is not a fixed-gain "
                                 f"actuator with no or affine bias")
            # force = gain * ctrl + bias0 (+ bias1 * length + bias2 * velocity, zero for a motor)
            model.actuator_biastype[i] = int(mujoco.mjtBias.mjBIAS_AFFINE)
            model.actuator_biasprm[i, 0] += offset[i] * model.actuator_gainprm[i, 0]
        dq = rotvec_quat(self.camera_rot_offset)
        for c in range(model.ncam):
            model.cam_pos[c] += np.asarray(self.camera_pos_offset)
            q = np.empty(4)
            mujoco.mju_mulQuat(q, model.cam_quat[c].copy(), dq)  # dq in the camera's own frame
            model.cam_quat[c] = q
        tool = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "tool")
        if tool >= 0:
            model.body_pos[tool] += np.asarray(self.tool_pos_offset)
            q = np.empty(4)
            mujoco.mju_mulQuat(q, model.body_quat[tool].copy(),
                               rotvec_quat(self.tool_rot_offset))
            model.body_quat[tool] = q
        elif any(self.tool_pos_offset) or any(self.tool_rot_offset):
            raise ValueError("Perturbation.tool_pos_offset/tool_rot_offset: the model has no body "
                             "named 'tool'")
        # MuJoCo C caches quantities derived from the masses at compile time, and some it steps
        # with: the mass of a "simple" dof (a body on slide joints, e.g. the push pusher or the
        # cartpole's cart) is ``dof_M0``, not the body's mass. Without recomputing them a mass
        # perturbation of such a body changed nothing the engine simulates (pusher mass x1.5: the
        # twin moved exactly as at x1). The contact regulariser's ``invweight0`` is kept nominal,
        # as in the simulator (MJX takes it from the nominal model whatever ``PhysParams`` says).
        invweight = {k: getattr(model, k).copy() for k in ("body_invweight0", "dof_invweight0")}
        mujoco.mj_setConst(model, mujoco.MjData(model))
        for k, v in invweight.items():
            getattr(model, k)[:] = v


def rotvec_quat(rotvec) -> np.ndarray:
    """Unit quaternion of an axis-angle vector."""
    rot = np.asarray(rotvec, np.float64)
    angle = float(np.linalg.norm(rot))
    dq = np.array([1.0, 0.0, 0.0, 0.0])
    if angle > 0:
        mujoco.mju_axisAngle2Quat(dq, rot / angle, angle)
    return dq
