"""Identifiable physical parameters as a pytree, applied to an ``mjx.Model``.

``PhysParams`` holds the quantities Real2Sim fits and Learn@Sim randomises: per-body mass (the
body's rotational inertia is scaled with it, so the mass distribution keeps its shape), per-dof
damping, armature and friction loss, per-geom sliding friction, per-actuator gain and bias, and
gravity. Values are physical (kg, N s/m, ...), so a table of them reads as a robot's datasheet.

Optimisers work on the *unconstrained* form (``unconstrain`` / ``constrain``): positive
fields (mass, friction, gain) through ``log``, non-negative fields (damping, armature, friction
loss) through a softplus, real fields (bias, gravity) as they are. So a gradient step can never
produce a negative mass. Building a ``PhysParams`` with concrete values that are negative or not
finite raises ``ValueError`` naming the field and index.

Zeros an MJCF writes into a positive field are part of the model, not values: a massless body (a
frame for a site or a camera, welded to its parent -- MuJoCo allows it for bodies without dofs), a
frictionless geom, an actuator of gain 0. ``from_model`` keeps them, ``apply`` and ``to_mjmodel``
write 0 there whatever the field holds (so the derivative there is 0), ``check_shapes`` refuses a
0 anywhere else, and sysid fits none of them.

Caveat inherited from MJX: friction-loss constraint rows exist only for dofs whose friction loss
is non-zero in the MJCF; on the other dofs ``frictionloss`` has no effect (and zero gradient).
"""

from __future__ import annotations

import dataclasses
from typing import Mapping

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

__all__ = ["PhysParams", "PhysParamsError", "POSITIVE", "NONNEGATIVE", "REAL", "position_servos"]

POSITIVE = ("mass", "friction", "gain")
NONNEGATIVE = ("damping", "armature", "frictionloss")
REAL = ("bias", "gravity")
# Floor for non-negative fields in unconstrained form (softplus^-1 of 0 is -inf).
_SOFTPLUS_FLOOR = 1e-9


class PhysParamsError(ValueError):
    """Parameters that do not fit a model (a field's shape, a 0 where the model has none); one
    line, naming the field."""


@dataclasses.dataclass(frozen=True)
class PhysParams:
    """Identifiable parameters of an MJCF model (shapes for a model with nbody, nv, ngeom, nu)."""

    mass: jax.Array
    """Mass of every body except the world body, kg, shape (nbody-1,), > 0 (0 only for a body
    massless in the MJCF: module docstring)."""
    damping: jax.Array
    """Joint damping per dof, shape (nv,), >= 0."""
    armature: jax.Array
    """Rotor inertia added to the mass matrix diagonal per dof, shape (nv,), >= 0."""
    frictionloss: jax.Array
    """Coulomb (dry) friction per dof, shape (nv,), >= 0."""
    friction: jax.Array
    """Sliding friction coefficient per geom, shape (ngeom,), > 0 (0 where the MJCF has 0)."""
    gain: jax.Array
    """Actuator gain (``gainprm[0]``), shape (nu,), > 0 (0 where the MJCF has 0)."""
    bias: jax.Array
    """Actuator bias (``biasprm[0:3]``: constant, * length, * velocity), shape (nu, 3)."""
    gravity: jax.Array
    """Gravity vector, m/s^2, shape (3,)."""

    def __post_init__(self):
        for name in POSITIVE + NONNEGATIVE + REAL:
            _check(name, getattr(self, name))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_model(cls, model: mujoco.MjModel, dtype=None) -> "PhysParams":
        """The nominal parameters written in an MJCF (compiled ``mujoco.MjModel``)."""
        dtype = dtype or (jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
        a = lambda x: jnp.asarray(np.array(x, dtype=np.float64), dtype=dtype)
        return cls(
            mass=a(model.body_mass[1:]),
            damping=a(model.dof_damping),
            armature=a(model.dof_armature),
            frictionloss=a(model.dof_frictionloss),
            friction=a(model.geom_friction[:, 0]),
            gain=a(model.actuator_gainprm[:, 0]),
            bias=a(model.actuator_biasprm[:, :3]),
            gravity=a(model.opt.gravity),
        )

    def expected_shapes(self, model: mujoco.MjModel) -> dict[str, tuple[int, ...]]:
        """The shape of each field for ``model`` (a compiled ``mujoco.MjModel``)."""
        return {"mass": (model.nbody - 1,), "damping": (model.nv,), "armature": (model.nv,),
                "frictionloss": (model.nv,), "friction": (model.ngeom,), "gain": (model.nu,),
                "bias": (model.nu, 3), "gravity": (3,)}

    def check_shapes(self, model: mujoco.MjModel, what: str = "this model") -> "PhysParams":
        """``self`` if every field has the shape ``model`` needs, else ``PhysParamsError`` naming
        the first field that does not, with the expected and given shapes (e.g. parameters of
        another task, or ``mass=[]``), or the first positive entry that is 0 where the model's is
        not. Returns ``self`` so it can be chained."""
        for name, want in self.expected_shapes(model).items():
            got = tuple(np.shape(getattr(self, name)))
            if got != want:
                raise PhysParamsError(
                    f"PhysParams.{name} has shape {got}; {what} needs {want} "
                    f"({_SHAPE_RULE[name]}): parameters of another model?")
        for name, zero in _model_zeros(model).items():
            v = np.asarray(getattr(self, name))
            bad = np.flatnonzero((v.reshape(-1) <= 0) & ~zero)
            if bad.size:
                i = int(bad[0])
                raise PhysParamsError(
                    f"PhysParams.{name}[{i}] is {v.reshape(-1)[i]:g} where {what} has "
                    f"{_model_field(model, name)[i]:g}: only an entry the MJCF itself makes 0 "
                    f"may be 0")
        return self

    def replace(self, **fields) -> "PhysParams":
        return dataclasses.replace(self, **fields)

    def scaled(self, **factors) -> "PhysParams":
        """A copy with fields multiplied by factors, e.g. ``p.scaled(mass=1.2, damping=0.5)``."""
        return self.replace(**{k: getattr(self, k) * v for k, v in factors.items()})

    def as_dict(self) -> dict[str, np.ndarray]:
        return {f.name: np.asarray(getattr(self, f.name)) for f in dataclasses.fields(self)}

    # ------------------------------------------------------------------ application
    def apply(self, m):
        """Return ``m`` (an ``mjx.Model``) with these parameters written in. Differentiable."""
        nominal_mass = m.body_mass[1:]
        # the model's own zeros stay zero (module docstring): a massless frame stays massless
        mass = jnp.where(nominal_mass > 0, self.mass, 0.0)
        friction = jnp.where(m.geom_friction[:, 0] > 0, self.friction, 0.0)
        gain = jnp.where(m.actuator_gainprm[:, 0] != 0, self.gain, 0.0)
        ratio = mass / jnp.where(nominal_mass > 0, nominal_mass, 1.0)
        return m.tree_replace({
            "body_mass": m.body_mass.at[1:].set(mass),
            "body_inertia": m.body_inertia.at[1:].multiply(ratio[:, None]),
            "dof_damping": self.damping,
            "dof_armature": self.armature,
            "dof_frictionloss": self.frictionloss,
            "geom_friction": m.geom_friction.at[:, 0].set(friction),
            "actuator_gainprm": m.actuator_gainprm.at[:, 0].set(gain),
            "actuator_biasprm": m.actuator_biasprm.at[:, :3].set(self.bias),
            "opt.gravity": self.gravity,
        })

    def to_mjmodel(self, model: mujoco.MjModel) -> mujoco.MjModel:
        """A copy of ``model`` (a compiled ``mujoco.MjModel``) with these parameters written in
        as ``apply`` writes them into an ``mjx.Model`` (a body's inertia scaled with its mass):
        for MuJoCo C, or saved as MJCF (``twinrl.envs.mjcf.save_mjcf``)."""
        import copy

        self.check_shapes(model)
        p = self.as_dict()
        for name in NONNEGATIVE:  # the reparameterisation's floor is a 0 (no friction-loss row)
            p[name] = np.where(p[name] <= 2 * _SOFTPLUS_FLOOR, 0.0, p[name])
        for name, zero in _model_zeros(model).items():  # the model's own zeros stay zero
            p[name] = np.where(zero, 0.0, p[name])
        m = copy.deepcopy(model)
        nominal = np.where(m.body_mass[1:] > 0, m.body_mass[1:], 1.0)
        m.body_inertia[1:] *= (p["mass"] / nominal)[:, None]
        m.body_mass[1:] = p["mass"]
        m.dof_damping[:] = p["damping"]
        m.dof_armature[:] = p["armature"]
        m.dof_frictionloss[:] = p["frictionloss"]
        m.geom_friction[:, 0] = p["friction"]
        m.actuator_gainprm[:, 0] = p["gain"]
        m.actuator_biasprm[:, :3] = p["bias"]
        m.opt.gravity[:] = p["gravity"]
        return m

    # ------------------------------------------------------------------ reparameterisation
    def unconstrain(self) -> dict[str, jax.Array]:
        """Unconstrained coordinates: log for positive, softplus^-1 for non-negative fields (a 0
        the model makes comes back as a tiny value, which ``apply`` writes as 0)."""
        out = {}
        for name in POSITIVE:  # the model's zeros (module docstring) at the floor, not -inf
            out[name] = jnp.log(jnp.maximum(getattr(self, name), _SOFTPLUS_FLOOR))
        for name in NONNEGATIVE:
            x = jnp.maximum(getattr(self, name), _SOFTPLUS_FLOOR)
            out[name] = x + jnp.log(-jnp.expm1(-x))  # softplus^-1, stable for small and large x
        for name in REAL:
            out[name] = getattr(self, name)
        return out

    @classmethod
    def constrain(cls, raw: Mapping[str, jax.Array]) -> "PhysParams":
        """Inverse of ``unconstrain``; any real input gives valid parameters."""
        fields = {}
        for name in POSITIVE:
            fields[name] = jnp.exp(raw[name])
        for name in NONNEGATIVE:
            fields[name] = jax.nn.softplus(raw[name])
        for name in REAL:
            fields[name] = raw[name]
        return cls(**fields)


def position_servos(model) -> np.ndarray:
    """(nu,) bool: the actuators of ``model`` (a ``mujoco.MjModel``) that are position servos,
    force = kp * ctrl - kp * q (- kv * qdot): an affine bias whose length term is minus the gain.
    Such a servo's stiffness is its gain *and* its bias' length term: a stiffness error scales
    both (the real twins' gain perturbation, sysid's ``gain/NAME``); the gain alone would move
    its set point."""
    gain = np.asarray(model.actuator_gainprm[:, 0])
    return ((np.asarray(model.actuator_biastype) == int(mujoco.mjtBias.mjBIAS_AFFINE))
            & np.isclose(np.asarray(model.actuator_biasprm[:, 1]), -gain) & (gain != 0))


def _model_field(model: mujoco.MjModel, name: str) -> np.ndarray:
    """A positive field's values in ``model`` (a compiled ``mujoco.MjModel``)."""
    return np.asarray({"mass": model.body_mass[1:], "friction": model.geom_friction[:, 0],
                       "gain": model.actuator_gainprm[:, 0]}[name], np.float64)


def _model_zeros(model: mujoco.MjModel) -> dict[str, np.ndarray]:
    """Each positive field's entries that ``model`` itself makes 0 (bool)."""
    return {name: _model_field(model, name) == 0 for name in POSITIVE}


_FIELDS = tuple(f.name for f in dataclasses.fields(PhysParams))
_SHAPE_RULE = {"mass": "nbody-1: every body but the world", "damping": "nv", "armature": "nv",
               "frictionloss": "nv", "friction": "ngeom", "gain": "nu", "bias": "nu, 3",
               "gravity": "3"}


def _flatten(p: PhysParams):
    return [(jax.tree_util.GetAttrKey(k), getattr(p, k)) for k in _FIELDS], None


def _unflatten(_, leaves) -> PhysParams:
    # JAX rebuilds PhysParams-shaped trees of gradients, tangents and sentinels: those are not
    # physical values, so they bypass the validation done by the constructor.
    p = object.__new__(PhysParams)
    for k, v in zip(_FIELDS, leaves):
        object.__setattr__(p, k, v)
    return p


jax.tree_util.register_pytree_with_keys(PhysParams, _flatten, _unflatten)


def _check(name: str, value) -> None:
    """Reject negative or non-finite concrete values; tracers (inside jit) pass through."""
    if isinstance(value, jax.core.Tracer) or not hasattr(value, "shape"):
        return
    try:
        v = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return  # not numeric (e.g. a sentinel used by tree utilities)
    bad = ~np.isfinite(v)
    if bad.any():
        raise ValueError(f"PhysParams.{name} has a non-finite value at index "
                         f"{tuple(int(i) for i in np.argwhere(bad)[0])}: {v[bad][0]}")
    if name in POSITIVE and (v < 0).any():  # 0: the model's own zeros (check_shapes)
        i = tuple(int(i) for i in np.argwhere(v < 0)[0])
        raise ValueError(f"PhysParams.{name} must be > 0, got {v[i]} at index {i}")
    if name in NONNEGATIVE and (v < 0).any():
        i = tuple(int(i) for i in np.argwhere(v < 0)[0])
        raise ValueError(f"PhysParams.{name} must be >= 0, got {v[i]} at index {i}")
