"""``System``: the identified twin as one pytree value (SAM-RL's "digital twin", HDS's identified
simulator), carried whole from Real2Sim to every trainer, checkpoint and evaluation.

A ``System`` holds what Real2Sim identifies about the real robot and scene:

- ``params``: the ``twinrl.physics.PhysParams`` (masses, damping, friction, gains, gravity);
- ``latency``: the action latency in control steps (static: it sets the shape of the action
  queue), applied by ``twinrl.envs.wrappers.LatencyWrapper``;
- ``cameras``: named ``twinrl.render.Camera`` poses and intrinsics (optional; visual Real2Sim);
- ``objects``: per object name, its pose/size/colour arrays (optional; visual Real2Sim);
- ``tool``: the tool's grasp in the hand (``ToolGrasp``: ``pos_offset``, ``rot_offset``,
  ``visual.fit_body_offset``'s; optional), where the arm tasks move their tool
  (``ArmTask.with_system``);
- ``controller``: the Cartesian controller's calibration (``ControllerCalibration``:
  ``joint_speed``, ``ArmTask.servo_speed`` of the identified parameters; optional).

On disk the tool's grasp and the controller's calibration are the ``objects`` entries ``"tool"``
and ``"controller"`` (the layout files have always had), and a ``System`` built with such entries
in ``objects`` takes them as its typed ``tool`` / ``controller``.

``envs.make(name, system=...)`` builds the simulated task from it, ``to_json``/``from_json`` write
and read it exactly (float64 values survive the round trip bit for bit), and every policy
checkpoint stores one, so ``twinrl eval`` rebuilds the simulator a policy was trained in.
``randomization_fn(system, rng)`` is Brax's domain-randomisation hook on it.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.envs.registry import TASKS
from twinrl.physics import PhysParams
from twinrl.physics.sim import load_mjcf
from twinrl.render import Camera
from twinrl.render.camera import mat_to_quat

__all__ = ["System", "SystemFormatError", "ToolGrasp", "ControllerCalibration", "randomization_fn",
           "system_of", "FORMAT", "FILENAME"]

FORMAT = "twinrl-system-1"
FILENAME = "system.json"
"""Name of a ``System``'s file beside a checkpoint's ``checkpoint.json``."""


class SystemFormatError(ValueError):
    """A ``System`` document that cannot be read (format, missing field, wrong type)."""


def _field(record: str, name: str, value, width: int | None):
    """``value`` as float64 NumPy (a JAX array, or a tracer, kept as it is: a system inside a
    trace or a batch), its last axis ``width`` long when given."""
    if not isinstance(value, jax.Array):
        value = np.asarray(value, np.float64)
    shape = np.shape(value)
    if len(shape) == 0 or (width is not None and shape[-1] != width):
        want = f"{width} numbers" if width is not None else "a vector"
        raise ValueError(f"{record}.{name} must be {want} (a leading batch axis allowed), got "
                         f"shape {shape}")
    return value


@dataclasses.dataclass(frozen=True, eq=False)
class ToolGrasp:
    """The tool's grasp in the hand, as identified (``visual.fit_body_offset`` of body ``tool``):
    how far the tool sits from where the MJCF puts it. ``Perturbation``'s ``tool_pos_offset`` /
    ``tool_rot_offset``; ``ArmTask.set_grasp`` moves the simulator's tool by it."""

    pos_offset: Any
    """Offset (m, (3,)) of the tool from its nominal position, in the hand's frame."""
    rot_offset: Any
    """Turn (axis-angle, rad, (3,)) of the tool from its nominal orientation, in its own frame."""

    def __post_init__(self):
        for f in ("pos_offset", "rot_offset"):
            object.__setattr__(self, f, _field("ToolGrasp", f, getattr(self, f), 3))


@dataclasses.dataclass(frozen=True, eq=False)
class ControllerCalibration:
    """The Cartesian controller's calibration to the identified servos
    (``ArmTask.calibrate_controller``, ``RealTwin.calibrate_controller``)."""

    joint_speed: Any
    """Per joint, how fast its servo closes a step of its target relative to the nominal arm's
    (``ArmTask.servo_speed`` of the identified parameters; ``CartesianController.joint_speed``)."""

    def __post_init__(self):
        object.__setattr__(self, "joint_speed",
                           _field("ControllerCalibration", "joint_speed", self.joint_speed, None))


_RECORDS = {"tool": ToolGrasp, "controller": ControllerCalibration}
"""The typed fields of a ``System`` and their record types; on disk, ``objects`` entries."""


@dataclasses.dataclass(frozen=True, eq=False)
class System:
    """The identified twin of a task (module docstring). A batch of systems (domain
    randomisation) is a ``System`` whose array leaves have a leading axis."""

    params: PhysParams
    """Physical parameters the simulator runs with."""
    latency: int = 0
    """Action latency in control steps (>= 0; static)."""
    task: str | None = None
    """Registered task name the system belongs to (static; ``envs.make`` checks it)."""
    cameras: Mapping[str, Camera] | None = None
    """Named cameras (pose + intrinsics), or None when not identified."""
    objects: Mapping[str, Mapping[str, jax.Array]] | None = None
    """Per object name, named arrays (e.g. ``pos``, ``quat``, ``size``, ``rgba``), or None.
    Entries ``"tool"`` and ``"controller"`` given here become ``tool`` and ``controller``."""
    tool: ToolGrasp | None = None
    """The tool's grasp in the hand (a ``ToolGrasp``, or a mapping of its fields), or None: the
    grasp the MJCF writes."""
    controller: ControllerCalibration | None = None
    """The Cartesian controller's calibration (a ``ControllerCalibration``, or a mapping of its
    fields), or None: the nominal controller."""

    def __post_init__(self):
        if not isinstance(self.params, PhysParams):
            raise TypeError(f"System.params must be a PhysParams, got {type(self.params).__name__}")
        lat = self.latency
        if isinstance(lat, bool) or not isinstance(lat, (int, np.integer)) or lat < 0:
            raise ValueError(f"System.latency must be an integer >= 0 control steps, got {lat!r}")
        object.__setattr__(self, "latency", int(lat))
        if self.task is not None and self.task not in TASKS:
            raise ValueError(f"System.task {self.task!r} is not a registered task; registered: "
                             f"{', '.join(TASKS)}")
        if self.cameras is not None:
            for k, c in self.cameras.items():
                if not isinstance(c, Camera):
                    raise TypeError(f"System.cameras[{k!r}] must be a render.Camera, got "
                                    f"{type(c).__name__}")
            object.__setattr__(self, "cameras", dict(self.cameras))
        objects = None if self.objects is None else {str(k): dict(v)
                                                     for k, v in self.objects.items()}
        for name, record in _RECORDS.items():
            value = getattr(self, name)
            if objects is not None and name in objects:
                if value is not None:
                    raise ValueError(f"System: {name} given twice, as System.{name} and as "
                                     f"objects[{name!r}]")
                value = objects.pop(name)
                if not objects:  # only typed entries: no objects of its own
                    objects = None
            if value is not None and not isinstance(value, record):
                if not isinstance(value, Mapping):
                    raise TypeError(f"System.{name} must be a {record.__name__} or a mapping of "
                                    f"its fields, got {type(value).__name__}")
                fields = {f.name for f in dataclasses.fields(record)}
                if set(value) != fields:
                    raise ValueError(f"System.{name} needs the fields {sorted(fields)}, got "
                                     f"{sorted(value)}")
                value = record(**value)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "objects", objects)

    # ------------------------------------------------------------------ construction
    @classmethod
    def nominal(cls, env_name: str, *, cameras: bool = False, width: int = 64,
                height: int = 64) -> "System":
        """The task's MJCF as written: nominal parameters (float64), no latency; with ``cameras``
        its named cameras (at the model's reference pose, ``width`` x ``height``)."""
        if env_name not in TASKS:
            raise ValueError(f"unknown task {env_name!r}; registered tasks are {', '.join(TASKS)}")
        env_class = TASKS[env_name].env_class
        model = load_mjcf(env_class.mjcf())
        params = _as_f64(PhysParams.from_model(model))
        cams = None
        if cameras:
            import mujoco

            data = mujoco.MjData(model)
            mujoco.mj_forward(model, data)
            cams = {c: _camera(model, data, c, width, height) for c in env_class.cameras}
        return cls(params=params, latency=0, task=env_name, cameras=cams)

    def replace(self, **fields: Any) -> "System":
        return dataclasses.replace(self, **fields)

    # ------------------------------------------------------------------ JSON
    def to_json(self) -> dict[str, Any]:
        """A JSON-able dict; ``from_json`` of it gives back every value exactly (float64)."""
        return {
            "format": FORMAT,
            "task": self.task,
            "latency": self.latency,
            "params": {k: _list(v) for k, v in self.params.as_dict().items()},
            "cameras": None if self.cameras is None else {
                k: {"pos": _list(c.pos), "quat": _list(c.quat), "fovy": _list(c.fovy),
                    "width": int(c.width), "height": int(c.height),
                    "principal": None if c.principal is None else _list(c.principal)}
                for k, c in self.cameras.items()},
            "objects": None if self._stored_objects() is None else {
                k: {f: _list(v) for f, v in o.items()} for k, o in self._stored_objects().items()},
        }

    def _stored_objects(self) -> dict[str, Mapping[str, Any]] | None:
        """``objects`` as the document stores it: with the typed records' entries."""
        typed = {name: {f.name: getattr(getattr(self, name), f.name)
                        for f in dataclasses.fields(record)}
                 for name, record in _RECORDS.items() if getattr(self, name) is not None}
        if self.objects is None and not typed:
            return None
        return {**(self.objects or {}), **typed}

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> "System":
        """The ``System`` of a ``to_json`` dict (arrays as float64 NumPy); the ``objects``
        entries ``"tool"`` and ``"controller"`` become ``tool`` and ``controller``."""
        if not isinstance(doc, Mapping):
            raise SystemFormatError(f"a System document must be a JSON object, got {type(doc).__name__}")
        if doc.get("format") != FORMAT:
            raise SystemFormatError(f"System document format {doc.get('format')!r}, expected {FORMAT!r}")
        try:
            params = PhysParams(**{k: _array(v) for k, v in doc["params"].items()})
            cams = doc.get("cameras")
            if cams is not None:
                cams = {k: Camera(pos=_array(c["pos"]), quat=_array(c["quat"]),
                                  fovy=_array(c["fovy"]), width=int(c["width"]),
                                  height=int(c["height"]),
                                  principal=None if c.get("principal") is None
                                  else _array(c["principal"]))
                        for k, c in cams.items()}
            objs = doc.get("objects")
            if objs is not None:
                objs = {k: {f: _array(v) for f, v in o.items()} for k, o in objs.items()}
            return cls(params=params, latency=int(doc.get("latency", 0)), task=doc.get("task"),
                       cameras=cams, objects=objs)
        except (KeyError, TypeError) as e:
            raise SystemFormatError(f"System document is missing or has a malformed field: "
                              f"{type(e).__name__}: {e}") from None

    def save(self, path: str | Path) -> Path:
        """Write ``to_json`` to ``path`` (a directory gets ``system.json``), atomically."""
        from twinrl.report import write_json

        path = Path(path)
        if path.is_dir():
            path = path / FILENAME
        return write_json(path, self.to_json())

    @classmethod
    def load(cls, path: str | Path) -> "System":
        """Read a ``System`` written by ``save`` (a directory: its ``system.json``)."""
        path = Path(path)
        if path.is_dir():
            path = path / FILENAME
        try:
            doc = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
            raise SystemFormatError(f"{path}: cannot read a System ({e})") from None
        return cls.from_json(doc)


# -------------------------------------------------------------------------------- pytree
_DATA = ("params", "cameras", "objects", "tool", "controller")


def _flatten(s: System):
    return ([(jax.tree_util.GetAttrKey(k), getattr(s, k)) for k in _DATA],
            (s.latency, s.task))


def _unflatten(aux, leaves) -> System:
    # Trees of gradients, tangents or batched tracers are not systems to validate.
    s = object.__new__(System)
    for k, v in zip(_DATA, leaves):
        object.__setattr__(s, k, v)
    object.__setattr__(s, "latency", aux[0])
    object.__setattr__(s, "task", aux[1])
    return s


jax.tree_util.register_pytree_with_keys(System, _flatten, _unflatten)


def _register_record(cls) -> None:
    """``cls`` (a record of arrays) as a pytree whose leaves are its fields; unflattening does not
    validate (trees of gradients, tangents or batched tracers)."""
    names = tuple(f.name for f in dataclasses.fields(cls))

    def flatten(r):
        return [(jax.tree_util.GetAttrKey(k), getattr(r, k)) for k in names], None

    def unflatten(_, leaves):
        r = object.__new__(cls)
        for k, v in zip(names, leaves):
            object.__setattr__(r, k, v)
        return r

    jax.tree_util.register_pytree_with_keys(cls, flatten, unflatten)


for _record in _RECORDS.values():
    _register_record(_record)


# -------------------------------------------------------------------------------- helpers
def system_of(env) -> System:
    """The ``System`` an env simulates: the one it was made from (``envs.make(system=...)``),
    else its parameters (or the MJCF's) with the latency of any ``LatencyWrapper`` around it."""
    s = getattr(env, "sys", None)
    if isinstance(s, System):
        return s
    latency = int(getattr(env, "latency", 0) or 0)
    inner = env
    while hasattr(inner, "env") and not hasattr(inner, "sim"):
        inner = inner.env
    params = inner.params if inner.params is not None else PhysParams.from_model(inner.sim.mj_model)
    name = getattr(inner, "name", None)
    return System(params=_as_f64(params), latency=latency, task=name if name in TASKS else None)


def randomization_fn(system: System, rng: jax.Array, *,
                     mass_scale: tuple[float, float] = (0.8, 1.25),
                     friction_scale: tuple[float, float] = (0.8, 1.25)):
    """Brax's domain-randomisation hook: ``(systems, in_axes)`` for a batch of keys ``rng``.

    Each system has every body mass and every geom friction multiplied by its own factor, drawn
    log-uniformly from ``mass_scale`` / ``friction_scale``; the other fields are shared (``in_axes``
    None). Pass ``functools.partial(randomization_fn, mass_scale=...)`` as Brax's
    ``randomization_fn`` (its trainers bind ``rng`` to one key per environment).
    """
    if not isinstance(system, System):
        raise TypeError(f"randomization_fn needs a System (build the env with "
                        f"envs.make(name, system=...)), got {type(system).__name__}")
    rng = jnp.asarray(rng)
    if jnp.issubdtype(rng.dtype, jax.dtypes.prng_key):
        batch = rng.shape
    else:
        batch = rng.shape[:-1]
    if len(batch) != 1:
        raise ValueError(f"rng must be a batch of keys (n,) or (n, 2), got shape {rng.shape}")
    for name, (lo, hi) in (("mass_scale", mass_scale), ("friction_scale", friction_scale)):
        if not 0 < lo <= hi:
            raise ValueError(f"{name} must be (low, high) with 0 < low <= high, got {(lo, hi)}")
    p = system.params

    def one(key):
        km, kf = jax.random.split(key)
        mass = jnp.asarray(p.mass) * _log_uniform(km, jnp.shape(p.mass), mass_scale)
        friction = jnp.asarray(p.friction) * _log_uniform(kf, jnp.shape(p.friction),
                                                          friction_scale)
        return mass, friction

    mass, friction = jax.vmap(one)(rng)
    n = batch[0]
    shared = {k: v for k, v in p.as_dict().items() if k not in ("mass", "friction")}
    params = _raw_params(p, mass=mass, friction=friction, **{
        k: jnp.broadcast_to(jnp.asarray(v), (n,) + np.shape(v)) for k, v in shared.items()})
    in_axes = _rebuild(jax.tree.map(lambda _: None, system),
                       _raw_params(p, **{k: 0 for k in p.as_dict()}))
    return _rebuild(system, params), in_axes


def _rebuild(system: System, params) -> System:
    s = object.__new__(System)
    for f in dataclasses.fields(System):
        object.__setattr__(s, f.name, getattr(system, f.name))
    object.__setattr__(s, "params", params)
    return s


def _raw_params(like: PhysParams, **fields) -> PhysParams:
    """A PhysParams-shaped tree of ``fields`` without validation (batched arrays, in_axes
    markers): JAX's unflatten, as for trees of gradients."""
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(like),
                                        [fields[f.name] for f in dataclasses.fields(PhysParams)])


def _log_uniform(key, shape, bounds):
    lo, hi = np.log(bounds[0]), np.log(bounds[1])
    return jnp.exp(jax.random.uniform(key, shape, minval=lo, maxval=hi))


def _as_f64(p: PhysParams) -> PhysParams:
    return PhysParams(**{k: np.asarray(v, np.float64) for k, v in p.as_dict().items()})


def _list(x):
    return np.asarray(x, np.float64).tolist()


def _array(x) -> np.ndarray:
    return np.asarray(x, np.float64)


def _camera(model, data, name: str, width: int, height: int) -> Camera:
    """MuJoCo's camera ``name`` as a float64 NumPy ``Camera`` (``Camera.create`` would cast to
    JAX's default float)."""
    import mujoco

    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
    return Camera(pos=np.array(data.cam_xpos[i], np.float64),
                  quat=mat_to_quat(data.cam_xmat[i]), fovy=np.asarray(float(model.cam_fovy[i])),
                  width=int(width), height=int(height))
