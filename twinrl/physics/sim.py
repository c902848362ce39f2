"""``Sim``: an MJCF compiled for MJX, stepped and rolled out as pure JAX functions.

``Sim`` is a plain Python object that holds the compiled model; its methods are pure functions of
pytrees (``mjx.Data``, action arrays, ``PhysParams``), so they can be jitted, vmapped and
differentiated. Every step goes through ``twinrl.physics.integrator.step`` (fixed-iteration
constraint solve, gradient-correct rotation update) so reverse-mode gradients exist through
contacts and joint limits; its forward results equal stock ``mjx.step`` (``Sim.stock_step`` is
kept for comparison).
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from pathlib import Path
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx
from mujoco.mjx._src.types import GeomType

from twinrl.physics import collision, gradients, integrator, solver
from twinrl.physics.mjwarn import MuJoCoWarning, mujoco_warnings
from twinrl.physics.params import PhysParams
from twinrl.physics.scenes import SCENES, scene_path

__all__ = ["Sim", "Trajectory", "MJCFError", "load_mjcf", "CONTACT_BOUNDS"]


class MJCFError(ValueError):
    """An MJCF that is missing, unreadable or that MuJoCo rejects."""


CONTACT_BOUNDS = ("max_geom_pairs", "max_contact_points")
"""MJX's own bounds on the contacts it evaluates, as ``<custom><numeric>`` fields of the MJCF:
``max_geom_pairs`` keeps, of each collision function's geom pairs (planes and height fields
excepted), the ones whose bounding spheres are nearest; ``max_contact_points`` keeps the deepest
contacts of each contact dimension. MJX has no broad phase: without them it evaluates every
candidate pair every step (the Control Suite's dog: 7,951)."""


def load_mjcf(mjcf: str | os.PathLike, **bounds: int | None) -> mujoco.MjModel:
    """Compile an MJCF given as a bundled scene name, a file path, or an XML string.

    ``bounds``: ``CONTACT_BOUNDS`` to set (or add) in the model's ``<custom><numeric>``
    fields; ``None`` leaves the MJCF's own.
    """
    unknown = set(bounds) - set(CONTACT_BOUNDS)
    if unknown:
        raise TypeError(f"unknown contact bound(s) {sorted(unknown)}: "
                        f"{', '.join(CONTACT_BOUNDS)}")
    bounds = {k: int(v) for k, v in bounds.items() if v is not None}
    for k, v in bounds.items():
        if v < 1:
            raise ValueError(f"{k} must be >= 1, got {v}")
    model = _load_mjcf(mjcf)
    if not bounds:
        return model
    # the bounds are numeric fields, which only a spec can add: the same source, edited
    spec = (mujoco.MjSpec.from_string(str(mjcf)) if str(mjcf).lstrip().startswith("<")
            else mujoco.MjSpec.from_file(str(scene_path(str(mjcf)) if str(mjcf) in SCENES
                                             else mjcf)))
    for k, v in bounds.items():
        numeric = spec.numeric(k)
        if numeric is None:
            spec.add_numeric(name=k, data=[float(v)])
        else:
            numeric.data = [float(v)]
    with mujoco_warnings(str(mjcf)[:80]):
        return spec.compile()


def _load_mjcf(mjcf: str | os.PathLike) -> mujoco.MjModel:
    text = str(mjcf)
    if not text.strip():
        # Path("") is ".", which would be reported as "a directory"
        raise MJCFError(f"the MJCF path is empty: give a bundled scene ({', '.join(SCENES)}), "
                        "the path of an MJCF file, or an XML string")
    if isinstance(mjcf, str) and text in SCENES:
        path = scene_path(text)
    elif isinstance(mjcf, str) and text.lstrip().startswith("<"):
        try:
            with mujoco_warnings("the MJCF string"):
                return mujoco.MjModel.from_xml_string(text)
        except ValueError as e:
            raise MJCFError(f"malformed MJCF string: {_first_line(e)}") from None
    else:
        path = Path(mjcf)
        if not path.exists() and path.suffix.lower() != ".xml" and len(path.parts) == 1:
            raise MJCFError(f"unknown scene {text!r}: bundled scenes are {', '.join(SCENES)}; "
                            "or give the path of an MJCF file")
    if not path.exists():
        raise MJCFError(f"MJCF file not found: {path} (bundled scenes: {', '.join(SCENES)})")
    if path.is_dir():
        raise MJCFError(f"MJCF path is a directory, not a file: {path}")
    try:
        with mujoco_warnings(str(path)):
            return mujoco.MjModel.from_xml_path(str(path))
    except ValueError as e:
        raise MJCFError(f"malformed MJCF {path}: {_first_line(e)}") from None


# Options MJX refuses that only report, changing nothing the simulation computes: the model is
# simulated with them off, said once (a ``MuJoCoWarning``). Options that change the dynamics
# (override of contact parameters, exact diagonal) stay refused.
_REPORTING = {int(mujoco.mjtEnableBit.mjENBL_ENERGY): "energy (mjENBL_ENERGY)",
              int(mujoco.mjtEnableBit.mjENBL_FWDINV): "fwdinv (mjENBL_FWDINV)"}


def put_model(mj_model: mujoco.MjModel, name: str = "mjcf") -> mjx.Model:
    """``mjx.put_model``, with what MJX cannot simulate (a geom pair without a collision
    function, an integrator, cone or solver it lacks, flex, some contact sensors) as one
    ``MJCFError`` naming the model and, for a collision pair, its geoms. A flag that only
    reports (energy, fwdinv) is turned off for MJX with a warning; ``mj_model`` keeps it."""
    flags = int(mj_model.opt.enableflags)
    off = [what for bit, what in _REPORTING.items() if flags & bit]
    if off:
        warnings.warn(f"{name}: MJX (mujoco {mujoco.__version__}) does not implement the "
                      f"reporting flag{'s' if len(off) > 1 else ''} {', '.join(off)}: simulated "
                      "without it (it changes no state)", MuJoCoWarning, stacklevel=2)
        mj_model.opt.enableflags = flags & ~sum(_REPORTING)
    try:
        with collision.mjx_pairs():  # the pairs MJX lacks, collided by twinrl's functions
            # MJX's default device is jax.devices()[0], another process's under jax.distributed
            return mjx.put_model(mj_model, device=jax.local_devices()[0])
    except NotImplementedError as e:
        msg = _first_line(e)
        if "collisions not implemented" in msg:
            pairs = _unsupported_pairs(mj_model) or [msg.split(" collisions")[0]]
            more = f" and {len(pairs) - 3} more" if len(pairs) > 3 else ""
            raise MJCFError(f"{name}: MJX (mujoco {mujoco.__version__}) has no collision "
                            f"function for {'; '.join(pairs[:3])}{more}: give one of the geoms "
                            "a type it pairs with (e.g. a box or a convex mesh for a moving "
                            "height field), or exclude the pair (contype/conaffinity, or "
                            "<contact><exclude>)") from None
        said = "not implemented" in msg or "not supported" in msg
        raise MJCFError(f"{name}: MJX (mujoco {mujoco.__version__}) cannot simulate this "
                        f"model: {msg if said else msg + ' is not implemented there'}") from None
    finally:
        mj_model.opt.enableflags = flags


def _unsupported_pairs(m: mujoco.MjModel) -> list[str]:
    """``"cylinder 'a' x box 'b'"`` for each colliding geom pair twinrl has no function for
    (MJX's pair filter; empty if that internal API differs)."""
    try:
        from mujoco.mjx._src import collision_driver as cd
        pairs = [(g1, g2) for g1, g2, _ in cd.geom_pairs(m)
                 if not collision.has_function(*(GeomType(int(t)) for t in m.geom_type[[g1, g2]]))]
    except Exception:  # noqa: BLE001  (only the message's detail depends on it)
        return []

    def label(g):
        kind = mujoco.mjtGeom(int(m.geom_type[g])).name.removeprefix("mjGEOM_").lower()
        geom = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, int(g))
        body = mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, int(m.geom_bodyid[g]))
        where = repr(geom) if geom else f"#{int(g)}" + (f" of body {body!r}" if body else "")
        return f"{kind} {where}"
    return [f"{label(a)} x {label(b)}" for a, b in pairs]


def _first_line(e: Exception) -> str:
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return " ".join(lines[:3]) if lines else type(e).__name__


class Trajectory(NamedTuple):
    """Per-step physics state of a rollout; leading axis is time (state *after* each step)."""

    qpos: jax.Array
    qvel: jax.Array
    n_active: jax.Array
    """Limit and contact rows carrying force at each step (0 = free of limits and contacts);
    equality and friction-loss rows are not counted."""


@dataclasses.dataclass(frozen=True, eq=False)
class Sim:
    """An MJCF compiled for MJX.

    Args:
      mjcf: bundled scene name, MJCF path or XML string.
      frame_skip: physics steps per control step.
      iterations: constraint-solver iterations (default: the MJCF's ``<option iterations>``).
        The differentiable solve always runs this many (no-ops after convergence), so keep it
        small; MuJoCo's default of 100 is far more than small scenes need.
      ls_iterations: line-search iterations (default: the MJCF's).
      gradient: how reverse mode goes through the constraint solve: ``"implicit"`` (default:
        the derivative of the converged solution, by the implicit function theorem) or
        ``"unrolled"`` (the derivative of the fixed iterations; wrong by orders of magnitude
        where a solve's line search switches pieces, e.g. a box landing flat). The forward is
        the same either way. See ``twinrl.physics.solver``.
      contacts: collision rules: ``"mjx"`` (default, stock MJX's) or ``"mujoco"`` (a box on a
        plane touches with every lower corner, as MuJoCo C makes it; MJX keeps only corners
        within 1 mm of the deepest). See ``twinrl.physics.collision``.
      max_geom_pairs, max_contact_points: MJX's bounds on the contacts evaluated per step
        (``CONTACT_BOUNDS``), set in the model; default: the MJCF's own, if any.
    """

    mj_model: mujoco.MjModel
    model: mjx.Model
    frame_skip: int = 1
    name: str = "mjcf"
    gradient: str = "implicit"
    bundled: bool = False
    """Loaded by a bundled scene's name (not a user's file that happens to share it)."""
    contacts: str = "mjx"

    @classmethod
    def load(cls, mjcf, *, frame_skip: int = 1, iterations: int | None = None,
             ls_iterations: int | None = None, name: str | None = None,
             gradient: str = "implicit", contacts: str = "mjx",
             max_geom_pairs: int | None = None,
             max_contact_points: int | None = None) -> "Sim":
        if frame_skip < 1:
            raise ValueError(f"frame_skip must be >= 1, got {frame_skip}")
        if gradient not in solver.GRADIENTS:
            raise ValueError(f"gradient must be one of {', '.join(solver.GRADIENTS)}, "
                             f"got {gradient!r}")
        collision.check_contacts(contacts)
        for what, n in (("iterations", iterations), ("ls_iterations", ls_iterations)):
            if n is not None and int(n) < 1:
                raise ValueError(f"{what} must be >= 1, got {n}")
        mj_model = load_mjcf(mjcf, max_geom_pairs=max_geom_pairs,
                             max_contact_points=max_contact_points)
        if iterations is not None:
            mj_model.opt.iterations = int(iterations)
        if ls_iterations is not None:
            mj_model.opt.ls_iterations = int(ls_iterations)
        if name is None:
            name = str(mjcf) if (isinstance(mjcf, str) and mjcf in SCENES) else (
                Path(str(mjcf)).stem if not str(mjcf).lstrip().startswith("<") else "mjcf")
        return cls(mj_model=mj_model, model=put_model(mj_model, name), frame_skip=frame_skip,
                   name=name, gradient=gradient,
                   bundled=isinstance(mjcf, str) and mjcf in SCENES, contacts=contacts)

    def recompiled(self, mj_model: mujoco.MjModel) -> "Sim":
        """The same simulator (frame skip, name, gradient mode, contacts) on an edited
        ``mj_model``."""
        return dataclasses.replace(self, mj_model=mj_model, model=put_model(mj_model, self.name))

    # ------------------------------------------------------------------ shapes
    @property
    def nq(self) -> int: return self.mj_model.nq
    @property
    def nv(self) -> int: return self.mj_model.nv
    @property
    def nu(self) -> int: return self.mj_model.nu
    @property
    def dt(self) -> float:
        """Control period: timestep * frame_skip."""
        return float(self.mj_model.opt.timestep) * self.frame_skip

    @property
    def ctrl_range(self) -> np.ndarray:
        """(nu, 2) lower/upper control bounds (+-inf where unlimited)."""
        r = np.array(self.mj_model.actuator_ctrlrange, dtype=np.float64)
        lim = np.array(self.mj_model.actuator_ctrllimited, dtype=bool)
        r[~lim] = [-np.inf, np.inf]
        return r

    def default_params(self) -> PhysParams:
        return PhysParams.from_model(self.mj_model)

    # ------------------------------------------------------------------ state
    def init(self, qpos=None, qvel=None) -> mjx.Data:
        """A fresh ``mjx.Data`` at ``qpos``/``qvel`` (default: the model's ``qpos0``, rest)."""
        with collision.mjx_pairs():  # MJX sizes the contacts of every pair by its table
            d = mjx.make_data(self.model, device=jax.local_devices()[0])  # this process's
        if qpos is not None:
            d = d.replace(qpos=jnp.asarray(qpos, d.qpos.dtype).reshape(self.nq))
        if qvel is not None:
            d = d.replace(qvel=jnp.asarray(qvel, d.qvel.dtype).reshape(self.nv))
        return d

    def model_with(self, params: PhysParams | None) -> mjx.Model:
        return self.model if params is None else params.apply(self.model)

    # ------------------------------------------------------------------ dynamics
    def step(self, data: mjx.Data, action: jax.Array, params: PhysParams | None = None,
             *, iterations: int | None = None) -> mjx.Data:
        """One control step (``frame_skip`` physics steps) with ``ctrl = action``."""
        m = self.model_with(params)
        d = data.replace(ctrl=jnp.asarray(action, data.ctrl.dtype).reshape(self.nu))
        step = lambda d: _step(m, d, iterations, self.gradient, self.contacts)
        if self.frame_skip == 1:
            return step(d)
        d, _ = jax.lax.scan(lambda d, _: (step(d), None), d, None, length=self.frame_skip)
        return d

    def stock_step(self, data: mjx.Data, action: jax.Array,
                   params: PhysParams | None = None) -> mjx.Data:
        """The same control step through stock ``mjx.step`` (forward only, not reverse-AD-able)."""
        m = self.model_with(params)
        d = data.replace(ctrl=jnp.asarray(action, data.ctrl.dtype).reshape(self.nu))
        for _ in range(self.frame_skip):
            d = integrator.same_dtypes(mjx.step(m, d), d)  # scannable with tendons in x64
        return d

    def rollout(self, data: mjx.Data, actions: jax.Array, params: PhysParams | None = None,
                *, truncate: int | None = None,
                step_fn: Callable | None = None) -> tuple[mjx.Data, Trajectory]:
        """Open-loop rollout (``lax.scan``) of ``actions`` (T, nu) from ``data``.

        Args:
          truncate: if set, stop gradients through the state every ``truncate`` steps
            (truncated backpropagation through time; see ``twinrl.physics.gradients``).
          step_fn: alternative ``(data, action, params) -> data`` (e.g. ``stock_step``).
        Returns:
          final ``mjx.Data`` and the ``Trajectory`` of states after each step.
        """
        step = step_fn or self.step
        T = actions.shape[0]

        def body(d, xs):
            t, a = xs
            d = gradients.truncate(d, t, truncate)
            d = step(d, a, params)
            return d, Trajectory(d.qpos, d.qvel, _n_active(d))

        return jax.lax.scan(body, data, (jnp.arange(T), actions))


# One physics step as a jitted function of (model, data): inside an outer trace it is a call whose
# jaxpr JAX traces once per process (per shapes and static arguments) and whose derivatives and
# batched forms it caches too, instead of retracing the step -- thousands of operations -- in
# every function that steps a scene. Measured (``bench/trace_reuse.py`` (in git history), peg insertion, 8 steps):
# a second vmapped rollout gradient traced in 3.1 s instead of 14.6 s. The model's arrays are
# arguments (its NumPy fields are static metadata of the ``mjx.Model`` pytree).
_step = jax.jit(integrator.step, static_argnums=(2, 3, 4))


def _n_active(d: mjx.Data) -> jax.Array:
    f = d._impl.efc_force[d._impl.ne + d._impl.nf:]
    return jnp.sum(f != 0) if f.size else jnp.zeros((), jnp.int32)
