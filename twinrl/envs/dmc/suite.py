"""The DeepMind Control Suite's models, reward tools and kinematics, for twinrl's ``dmc/`` tasks.

The models are the ``dm-control`` wheel's own XML files (``dm_control/suite/<domain>.xml``),
read from the installed package (located with ``importlib``, so dm_control itself is not
imported), never copies: ``suite_xml`` inlines their ``<include file="./common/...">`` assets
(materials, skybox, visual) and applies a task's edits (``SuiteTask.edit``) on the parsed tree,
returning one XML string both the simulator (MJX) and the real twin (MuJoCo C) compile. Edits
every domain gets: the ``energy`` flag is dropped (it only reports; MJX refuses it) and so is
``<sensor>`` (the rewards and observations are computed from the state here, so the simulator
does not spend a pass on sensors nobody reads).

``tolerance`` is dm_control's ``rewards.tolerance`` in ``jax.numpy`` with its sigmoids: the same
value everywhere (1 inside the bounds, the sigmoid of the distance to the nearest bound, over
``margin``, outside, a step when ``margin`` is 0), written so that its gradient is finite with
infinite bounds (a ``jnp.where`` branch holding ``x - inf`` would give NaN gradients).

``SuiteTask`` is the ``Env`` every ``dmc/`` task subclasses: its scene is the suite's XML, its
body frames come from ``frames(qpos)`` (twinrl's kinematics on the nominal model) and a
subtree's centre-of-mass velocity (the suite's ``subtreelinvel`` sensor) from
``subtree_linvel``. Rewards are functions of ``(qpos, qvel, action)`` like every twinrl task's,
so the real twin evaluates the same ones.
"""

from __future__ import annotations

import functools
import importlib.util
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Callable, ClassVar

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from twinrl.envs.base import Env
from twinrl.physics import smooth
from twinrl.physics.collision import collision

_HINGE, _SLIDE = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)

__all__ = ["suite_dir", "suite_xml", "find", "tolerance", "randomize_joints", "SuiteTask"]

DM_CONTROL_PIN = "dm-control==1.0.50"
"""The newest dm-control whose MuJoCo requirement the pinned MuJoCo 3.17.0 meets (1.0.52 needs
MuJoCo >= 4.0.1; there is no 1.0.51)."""


def suite_dir() -> Path:
    """The installed ``dm_control/suite`` folder, where the suite's XML files are."""
    spec = importlib.util.find_spec("dm_control")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError(f"the dmc/ tasks read the Control Suite's models from the "
                                  f"dm-control wheel, which is not installed: pip install "
                                  f"{DM_CONTROL_PIN}")
    return Path(list(spec.submodule_search_locations)[0]) / "suite"


def _inline_includes(root: ET.Element, folder: Path) -> None:
    """Replace every ``<include file=...>`` under ``root`` by the children of that file's root."""
    for parent in list(root.iter()):
        for i, child in reversed(list(enumerate(parent))):
            if child.tag == "include":
                parent.remove(child)
                included = ET.parse(folder / child.attrib["file"]).getroot()
                for k, grandchild in enumerate(included):
                    parent.insert(i + k, grandchild)


@functools.lru_cache(maxsize=None)
def suite_xml(domain: str, edit: Callable[[ET.Element], None] | None = None) -> str:
    """The Control Suite's ``<domain>.xml`` from the installed wheel as one XML string: includes
    inlined, the ``energy`` flag and ``<sensor>`` dropped (module docstring), then ``edit``
    applied to the tree (a function of the root ``<mujoco>`` element, editing it in place)."""
    folder = suite_dir()
    path = folder / f"{domain}.xml"
    if not path.is_file():
        raise FileNotFoundError(f"the dm-control wheel has no model {domain!r} ({path})")
    root = ET.parse(path).getroot()
    _inline_includes(root, folder)
    for flag in root.iter("flag"):
        flag.attrib.pop("energy", None)
    for sensor in root.findall("sensor"):
        root.remove(sensor)
    if edit is not None:
        edit(root)
    return ET.tostring(root, encoding="unicode")


def find(root: ET.Element, tag: str, name: str) -> ET.Element:
    """The element ``<tag name=name>`` under ``root`` (for ``SuiteTask.edit``), or a KeyError."""
    for el in root.iter(tag):
        if el.get("name") == name:
            return el
    raise KeyError(f"no <{tag} name={name!r}> in the model")


# ---------------------------------------------------------------------- rewards
def _sigmoid(x, value_at_1: float, sigmoid: str):
    """dm_control's ``rewards._sigmoids`` for ``x >= 0``: 1 at 0, ``value_at_1`` at 1."""
    if sigmoid in ("cosine", "linear", "quadratic"):
        if not 0 <= value_at_1 < 1:
            raise ValueError(f"value_at_margin must be in [0, 1) for {sigmoid!r}, got {value_at_1}")
    elif not 0 < value_at_1 < 1:
        raise ValueError(f"value_at_margin must be in (0, 1) for {sigmoid!r}, got {value_at_1}")
    if sigmoid == "gaussian":
        return jnp.exp(-0.5 * (x * np.sqrt(-2 * np.log(value_at_1))) ** 2)
    if sigmoid == "hyperbolic":
        return 1 / jnp.cosh(x * np.arccosh(1 / value_at_1))
    if sigmoid == "long_tail":
        return 1 / ((x * np.sqrt(1 / value_at_1 - 1)) ** 2 + 1)
    if sigmoid == "reciprocal":
        return 1 / (jnp.abs(x) * (1 / value_at_1 - 1) + 1)
    if sigmoid == "tanh_squared":
        return 1 - jnp.tanh(x * np.arctanh(np.sqrt(1 - value_at_1))) ** 2
    if sigmoid in ("cosine", "linear", "quadratic"):
        scale = {"cosine": np.arccos(2 * value_at_1 - 1) / np.pi, "linear": 1 - value_at_1,
                 "quadratic": np.sqrt(1 - value_at_1)}[sigmoid]
        s = x * scale
        inside = jnp.abs(s) < 1
        s = jnp.where(inside, s, 0.0)  # outside: a constant 0 (no gradient through cos etc.)
        value = {"cosine": lambda: (1 + jnp.cos(np.pi * s)) / 2, "linear": lambda: 1 - s,
                 "quadratic": lambda: 1 - s**2}[sigmoid]()
        return jnp.where(inside, value, 0.0)
    raise ValueError(f"unknown sigmoid {sigmoid!r}")


def tolerance(x, bounds: tuple[float, float] = (0.0, 0.0), margin: float = 0.0,
              sigmoid: str = "gaussian", value_at_margin: float = 0.1):
    """dm_control's ``rewards.tolerance`` in ``jax.numpy``: 1 where ``bounds[0] <= x <=
    bounds[1]``, else ``sigmoid(distance to the nearest bound / margin)`` falling to
    ``value_at_margin`` at ``margin``; ``margin = 0``: 0 outside (a step, no gradient). Bounds,
    margin and sigmoid are Python constants. Differentiable where the suite's is smooth
    (``gaussian`` and the other tails are C1 at the bounds; ``linear`` has a kink there)."""
    lower, upper = bounds
    if lower > upper:
        raise ValueError(f"lower bound {lower} > upper bound {upper}")
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    x = jnp.asarray(x)
    in_bounds = (lower <= x) & (x <= upper)
    if margin == 0:
        return jnp.where(in_bounds, 1.0, 0.0).astype(x.dtype)
    # the distance to the nearest bound, finite (and of finite gradient) with infinite bounds
    d = (jnp.maximum(lower - x, 0.0) + jnp.maximum(x - upper, 0.0)) / margin
    return jnp.where(in_bounds, 1.0, _sigmoid(d, value_at_margin, sigmoid)).astype(x.dtype)


def randomize_joints(m: mujoco.MjModel, rng: jax.Array, qpos: jax.Array) -> jax.Array:
    """dm_control's ``randomizers.randomize_limited_and_rotational_joints`` for hinge and slide
    joints: a limited joint uniform in its range, an unlimited hinge uniform in [-pi, pi], an
    unlimited slide left as it is in ``qpos``."""
    out = qpos
    keys = jax.random.split(rng, m.njnt)
    for j in range(m.njnt):
        kind, adr = int(m.jnt_type[j]), int(m.jnt_qposadr[j])
        if kind not in (_HINGE, _SLIDE):
            raise NotImplementedError(f"randomize_joints: joint {j} is not a hinge or a slide")
        if m.jnt_limited[j]:
            lo, hi = (float(v) for v in m.jnt_range[j])
        elif kind == _HINGE:
            lo, hi = -np.pi, np.pi
        else:
            continue
        out = out.at[adr].set(jax.random.uniform(keys[j], (), out.dtype, lo, hi))
    return out


# ---------------------------------------------------------------------- the task base
class SuiteTask(Env):
    """A Control Suite task on the wheel's XML (module docstring). Subclasses set ``domain`` and
    may edit the model (``edit``); the rest is ``Env``'s."""

    domain: ClassVar[str]
    """The suite's domain: its model is ``dm_control/suite/<domain>.xml``."""

    @staticmethod
    def edit(root: ET.Element) -> None:
        """Edit the parsed model in place before it is compiled (default: nothing)."""

    @classmethod
    def mjcf(cls) -> str:
        return suite_xml(cls.domain, cls.edit)

    @property
    def observation_size(self) -> int:
        # the observation of the model's rest state: no reset is traced (a settling rollout)
        m = self.sim.mj_model
        shape = jax.eval_shape(self.observe, jnp.asarray(m.qpos0, jnp.float32),
                               jnp.zeros(m.nv, jnp.float32)).shape
        return int(shape[-1])

    def body(self, name: str) -> int:
        """The id of body ``name`` of the model (a KeyError naming it if there is none)."""
        i = mujoco.mj_name2id(self.sim.mj_model, mujoco.mjtObj.mjOBJ_BODY, name)
        if i < 0:
            raise KeyError(f"{self.name}: no body {name!r}")
        return i

    def geom(self, name: str) -> int:
        """The id of geom ``name`` of the model."""
        i = mujoco.mj_name2id(self.sim.mj_model, mujoco.mjtObj.mjOBJ_GEOM, name)
        if i < 0:
            raise KeyError(f"{self.name}: no geom {name!r}")
        return i

    def frames(self, qpos: jax.Array):
        """``mjx.Data`` with the body, geom and site frames of ``qpos`` (``xpos``, ``xmat``,
        ``xipos``, ``geom_xpos``, ``site_xpos``, ...) on the nominal model."""
        return smooth.kinematics(self.sim.model, self.sim.init(qpos))

    def subtree_linvel(self, qpos: jax.Array, qvel: jax.Array, body: str) -> jax.Array:
        """The velocity of the centre of mass of ``body``'s subtree (MuJoCo's ``subtreelinvel``
        sensor), as the derivative of that centre along ``qvel`` (the suite's planar models
        have hinge and slide joints only, so ``d qpos / dt = qvel``)."""
        m = self.sim.mj_model
        if not np.isin(m.jnt_type, (_HINGE, _SLIDE)).all():
            raise NotImplementedError(f"{self.name}: subtree_linvel needs hinge/slide joints only")
        root = self.body(body)
        ids = [b for b in range(m.nbody) if _is_in_subtree(m.body_parentid, b, root)]
        mass = jnp.asarray(m.body_mass[ids], qpos.dtype)

        def com(q):
            return mass @ self.frames(q).xipos[np.asarray(ids)] / jnp.sum(mass)

        return jax.jvp(com, (qpos,), (qvel.astype(qpos.dtype),))[1]

    def penetrating(self, qpos: jax.Array) -> jax.Array:
        """Whether any two geoms interpenetrate at ``qpos`` (MuJoCo C would report a contact:
        ``ncon > 0``), by the simulator's collision functions."""
        d = collision(self.sim.model, self.frames(qpos), self.config.contacts)
        dist = d._impl.contact.dist
        return jnp.any(dist < 0) if dist.size else jnp.zeros((), bool)


def _is_in_subtree(parent: np.ndarray, body: int, root: int) -> bool:
    while body > 0 and body != root:
        body = int(parent[body])
    return body == root
