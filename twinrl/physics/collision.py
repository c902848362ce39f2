"""Collision detection for ``Sim``: stock MJX's, with derivatives for the SDF-searched pairs.

MJX (pinned mujoco-mjx 3.17.0, ``mujoco.mjx._src.collision_sdf``) collides pairs that involve a
cylinder or an ellipsoid with anything but a plane (sphere, capsule, ellipsoid, cylinder) by
searching the contact point: 10 steps of gradient descent with a line search on a clearance
function of the two shapes' signed distance functions (SDFs), then the distance and normal from
the SDFs and their gradients at the point found. Reverse mode through that search differentiates
the search steps (second derivatives of the SDFs at every step and the line search's argmin) and
the cylinder SDF's hand-written derivative, whose own derivative divides by ``|b| = 0`` inside the
shape: a 2-link capsule arm pressing a cylinder puck gave NaN in 102 of 118 gradient entries.

Here the pairs with a cylinder (sphere, capsule, ellipsoid or cylinder against a cylinder) run
the same search from the same starting points, with a cylinder SDF equal to MJX's whose first and
second derivatives are finite everywhere (no hand-written derivative; square roots guarded at
0), so reverse mode differentiates the search exactly as finite differences of the forward see
it. (Tried first and dropped: holding the searched point fixed and differentiating only the final
distance and normal -- finite, but 40-70 % off on resolved entries, because the point's motion
changes the normal.) The search is a heuristic with discrete choices (its line search takes an
argmin over 10 step sizes), so such a contact is piecewise smooth: ``twinrl gradcheck`` reports
entries whose perturbation switches a choice as kinks.

A height field against a sphere, a capsule, a box, a cylinder or an ellipsoid is
``twinrl.physics.hfield``'s (MJX's own sphere, capsule and box functions there differentiate to
wrong values: relative errors up to 1.5 against finite differences), an ellipsoid or a
cylinder against a box or a convex mesh ``twinrl.physics.polytopes``'; for the pairs among these that MJX lacks, ``mjx_pairs`` lends
MJX's own table their functions while ``Sim`` calls ``mjx.put_model`` and ``mjx.make_data``
(which check and size contacts by it), and takes them back after: stock MJX is left as it was.
Their forward is checked against MuJoCo C's.

Every other pair type is stock MJX's collision function, through the same driver loop
(``collision`` mirrors ``mujoco.mjx._src.collision_driver.collision`` with this table);
``fwd_position`` mirrors ``mujoco.mjx._src.forward.fwd_position`` with this ``collision``.
Forward results equal stock MJX's on those pairs (tested).

Contact rules (``CONTACTS``; ``Sim(contacts=...)``). ``"mjx"`` (default) is the above. ``"mujoco"``
replaces MJX's one rule that differs from MuJoCo C's: a box on a plane. MJX (``plane_convex``)
keeps only the box corners within a 1 mm skin of the deepest one (then the four spanning the
largest area): a box rocking a few degrees has corners 2-5 mm into the floor that get no
contact, and a corner's force jumps on or off as the deepest point moves by a millimetre.
MuJoCo C (``mjc_PlaneBox``) gives every corner on the plane's side of the box's centre its
contact, active as soon as it touches; this module's ``plane_box_mujoco`` does the same, so the
contact set changes only where a corner crosses the plane (the force is continuous there).
Measured on recorded states of the push real twin (MuJoCo C): one control step of MJX's rule
missed the box's velocity by up to 0.15 m/s (90th percentile 4e-3), this rule by 2e-5.
"""

from __future__ import annotations

import contextlib
import functools

import jax
import jax.numpy as jnp
from mujoco.mjx._src import collision_convex as _convex
from mujoco.mjx._src import collision_driver as _driver
from mujoco.mjx._src import collision_sdf as _sdf
from mujoco.mjx._src import constraint as _constraint
from mujoco.mjx._src import math as _math
from mujoco.mjx._src import smooth as _smooth
from mujoco.mjx._src.types import GeomType

from twinrl.physics import hfield as _hfield
from twinrl.physics import polytopes as _polytopes
from twinrl.physics import smooth as _tree
from twinrl.physics._shapes import cylinder_sdf

__all__ = ["collision", "fwd_position", "cylinder_sdf", "plane_box_mujoco", "check_contacts",
           "REFINED", "ADDED", "CONTACTS", "mjx_pairs", "has_function"]


# The cylinder pairs, as stock MJX builds them (same starting points, same search), with the
# cylinder SDF above: reverse mode then differentiates the search exactly, as finite differences
# of the forward see it, without NaN.
@_sdf.collider(ncon=1)
def _sphere_cylinder(s, c):
    return _sdf._optim(_sdf._sphere, cylinder_sdf, s, c, 0.5 * (s.pos + c.pos))


@_sdf.collider(ncon=2)
def _capsule_cylinder(ca, cy):
    mid, vec = 0.5 * (ca.pos + cy.pos), ca.mat[:, 2] * ca.size[1]
    optim = functools.partial(_sdf._optim, _sdf._capsule, cylinder_sdf, ca, cy)
    return jax.vmap(optim)(jnp.array([mid - vec, mid + vec]))


@_sdf.collider(ncon=1)
def _ellipsoid_cylinder(e, c):
    return _sdf._optim(_sdf._ellipsoid, cylinder_sdf, e, c, 0.5 * (e.pos + c.pos))


@_sdf.collider(ncon=4)
def _cylinder_cylinder(c1, c2):
    basis = _math.make_frame(c2.pos - c1.pos)
    mid, r = 0.5 * (c1.pos + c2.pos), jnp.maximum(c1.size[0], c2.size[0])
    x0 = jnp.array([mid + r * basis[1], mid + r * basis[2], mid - r * basis[1],
                    mid - r * basis[2]])
    optim = functools.partial(_sdf._optim, cylinder_sdf, cylinder_sdf, c1, c2)
    return jax.vmap(optim)(x0)


# The corners 0..3 of a box (sign bits x, y, z); corner 7 - i is the opposite of corner i.
_CORNERS = tuple((1.0 if i & 1 else -1.0, 1.0 if i & 2 else -1.0, 1.0 if i & 4 else -1.0)
                 for i in range(4))


@_convex.collider(ncon=4)
def plane_box_mujoco(plane, box):
    """Plane-box contacts as MuJoCo C makes them (``mjc_PlaneBox``): one per box corner on the
    plane's side of the box's centre (of each pair of opposite corners, the lower one), with
    the corner's signed distance; the constraint stage activates those within the margin, as C
    skips the others. Contact point halfway into the penetration, normal the plane's z."""
    n = plane.mat[:, 2]
    corner = (jnp.asarray(_CORNERS) * box.size) @ box.mat.T  # offsets from the box's centre
    corner = jnp.where((corner @ n <= 0.0)[:, None], corner, -corner)
    dist = jnp.dot(box.pos - plane.pos, n) + corner @ n
    pos = box.pos + corner - 0.5 * dist[:, None] * n
    return dist, pos, jnp.stack([_math.make_frame(n)] * 4, axis=0)


_REPLACED = {_sdf.sphere_cylinder: _sphere_cylinder, _sdf.capsule_cylinder: _capsule_cylinder,
             _sdf.ellipsoid_cylinder: _ellipsoid_cylinder,
             _sdf.cylinder_cylinder: _cylinder_cylinder}
_OURS = {**_hfield.FUNCTIONS, **_polytopes.FUNCTIONS}
ADDED = tuple(t for t in _OURS if t not in _driver._COLLISION_FUNC)
"""Geom-type pairs MJX 3.17 lacks, collided by ``twinrl.physics.hfield`` and ``polytopes``."""
# MJX sizes a pair's contacts from its own table's ``ncon`` (``make_condim``): a function here
# replacing one of MJX's must return as many
assert all(_driver._COLLISION_FUNC[t].ncon == f.ncon for t, f in _OURS.items() if t not in ADDED)
_FUNCTIONS = {**{types: _REPLACED.get(f, f) for types, f in _driver._COLLISION_FUNC.items()},
              **_OURS}
REFINED = tuple(types for types, f in _driver._COLLISION_FUNC.items() if f in _REPLACED)
"""Geom-type pairs collided with ``cylinder_sdf`` instead of MJX's ``_cylinder``."""
_RULES = {"mjx": _FUNCTIONS,
          "mujoco": {**_FUNCTIONS, (GeomType.PLANE, GeomType.BOX): plane_box_mujoco}}
CONTACTS = tuple(_RULES)
"""Contact rules: ``"mjx"`` (stock MJX's colliders) and ``"mujoco"`` (MuJoCo C's box on a plane)."""


@contextlib.contextmanager
def mjx_pairs():
    """MJX's own collision table with the pairs it lacks (``ADDED``), for the duration of a call
    into MJX that consults it -- ``mjx.put_model`` (it refuses a model with a pair missing there)
    and ``mjx.make_data`` (it sizes each pair's contacts from its function's ``ncon``) -- and
    exactly as before afterwards: importing or using twinrl leaves stock MJX as it was (tested).
    ``collision`` itself runs this module's table and needs none of it."""
    added = [t for t in ADDED if t not in _driver._COLLISION_FUNC]
    for t in added:
        _driver._COLLISION_FUNC[t] = _OURS[t]
    try:
        yield
    finally:
        for t in added:
            _driver._COLLISION_FUNC.pop(t, None)


def has_function(t1, t2) -> bool:
    """Whether twinrl collides geom types ``t1`` x ``t2`` (MJX's pairs and ``ADDED``)."""
    return (t1, t2) in _FUNCTIONS


def check_contacts(contacts: str) -> str:
    if contacts not in _RULES:
        raise ValueError(f"contacts must be one of {', '.join(CONTACTS)}, got {contacts!r}")
    return contacts


def collision(m, d, contacts: str = "mjx"):
    """``mjx`` collision with the refined SDF colliders (same driver loop as stock); ``contacts``
    picks the rule set (``CONTACTS``)."""
    table = _RULES[check_contacts(contacts)]
    if d._impl.ncon == 0:
        return d
    max_geom_pairs = _driver._numeric(m, "max_geom_pairs")
    max_contact_points = _driver._numeric(m, "max_contact_points")
    groups = _driver._contact_groups(m, d)
    for key, contact in groups.items():
        if (max_geom_pairs > -1 and contact.geom.shape[0] > max_geom_pairs
                and not set(key.types) & _driver._GEOM_NO_BROADPHASE):
            pos1, pos2 = d.geom_xpos[contact.geom.T]
            size1, size2 = m.geom_rbound[contact.geom.T]
            dist = jax.vmap(jnp.linalg.norm)(pos2 - pos1) - (size1 + size2)
            _, idx = jax.lax.top_k(-dist, k=max_geom_pairs)
            contact = jax.tree_util.tree_map(lambda x, idx=idx: x[idx], contact)
        func = table[key.types]
        dist, pos, frame = func(m, d, key, contact.geom)
        if func.ncon > 1:
            contact = jax.tree_util.tree_map(lambda x, r=func.ncon: jnp.repeat(x, r, axis=0),
                                             contact)
        groups[key] = contact.replace(dist=dist, pos=pos, frame=frame)

    condim_groups = {}
    for key, contact in groups.items():
        condim_groups.setdefault(key.condim, []).append(contact)
    if max_contact_points > -1:
        for key, contacts in condim_groups.items():
            contact = jax.tree_util.tree_map(lambda *x: jnp.concatenate(x), *contacts)
            if contact.geom.shape[0] > max_contact_points:
                _, idx = jax.lax.top_k(-contact.dist, k=max_contact_points)
                contact = jax.tree_util.tree_map(lambda x, idx=idx: x[idx], contact)
            condim_groups[key] = [contact]
    contacts = sum([condim_groups[k] for k in sorted(condim_groups)], [])
    contact = jax.tree_util.tree_map(lambda *x: jnp.concatenate(x), *contacts)
    return d.tree_replace({"_impl.contact": contact})


def fwd_position(m, d, contacts: str = "mjx"):
    """``mjx`` position stage with ``collision`` above."""
    d = _tree.kinematics(m, d)
    d = _tree.com_pos(m, d)
    d = _smooth.camlight(m, d)
    d = _smooth.tendon(m, d)
    d = _tree.crb(m, d)
    d = _smooth.tendon_armature(m, d)
    d = _smooth.factor_m(m, d)
    d = collision(m, d, contacts)
    d = _constraint.make_constraint(m, d)
    return _smooth.transmission(m, d)
