"""Contacts MJX 3.17 lacks between a box and an ellipsoid or a cylinder.

MJX (pinned mujoco-mjx 3.17.0) has no collision function for an ellipsoid or a cylinder against
a box (its SDF search covers the smooth pairs, its SAT the polytopes); ``mjx.put_model`` refuses
such a model ("no collision function for ellipsoid 'tail2' x box 'torso_massive'"). MuJoCo C
collides them with its convex penetration test (GJK/EPA), one contact, whose normal
``mjc_fixNormal`` then sets to the smooth geom's surface normal. This module collides them the
way ``twinrl.physics.hfield`` collides a height field -- the box's surface in place of the
field's, with the same candidates (``_shapes``), in the box's frame:

- face contacts: for each of the box's 6 faces whose plane the smooth geom's centre is outside
  of, the geom's support points along the face's inward normal (an ellipsoid's deepest point; a
  cylinder's rim points, a tripod per cap); a point counts where the face's rectangle holds its
  projection. Distance: the point's height over the face; normal: the face's.
- corner contacts: each of the box's 8 corners against the geom's SDF.
- edge contacts: each of the box's 12 edges at its point closest to the geom's centre in the
  geom's proportions, against the SDF.

No contact is deeper than the least of the faces' overlaps (moving the geom out through a face
by its overlap there separates the two); a candidate deeper than that is dropped. The ``NCON``
deepest are the pair's contacts: one where C makes its one (the deepest), more where a flat
face of the geom rests on the box (a cylinder's end on a box's face: its rim's tripod), so
that it rests as on a plane instead of rocking on one point. Differentiable as ``hfield``
(finite first and second derivatives; which face holds a point and which candidates are the
deepest are discrete choices: kinks).

Agreement with MuJoCo C (``tests/physics/test_boxes.py``, placed 2 mm deep): on a face, on an
edge and on a corner the deepest distance within 1e-6 m and positions within 2.5e-4 m; normals
within 1e-4 degree on a face, 2.1 degrees on an edge or a corner (C's is the geom's at the
midpoint of the penetration, an ellipsoid's by ray projection; ours the SDF's gradient at the
box's point). Dropped together onto a box landing on a plane (0.3 s, the box's plane contacts
as C makes them: ``contacts="mujoco"``), positions stay within 0.4 mm of C's. Not covered: a geom whose centre is inside the box (deeper than its own
half-size: no face candidate); a flat cylinder overhanging an edge, tilted, where neither C (1.9
mm along the face, for a part inside the box 3.8 cm wide and 1.8 cm high) nor the edge's point
here (11 mm) is the least translation that separates them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from mujoco.mjx._src import collision_convex as _convex
from mujoco.mjx._src import math as _math
from mujoco.mjx._src.types import GeomType

from twinrl.physics._shapes import (NO_CONTACT, cylinder_sdf, cylinder_support, edge_points,
                                    ellipsoid_sdf, ellipsoid_support, sdf_contacts)

__all__ = ["ellipsoid_box", "cylinder_box", "FUNCTIONS", "NCON"]

NCON = 4
"""Contacts per pair (the deepest of the candidates)."""

_FACES = jnp.concatenate([jnp.eye(3), -jnp.eye(3)])  # outward normals of the box's faces
_CORNERS = jnp.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
# the 12 edges: corner pairs differing in one coordinate (corner i's bit k: 4, 2, 1 for x, y, z)
_EDGES = jnp.array([(i, i | b) for b in (1, 2, 4) for i in range(8) if not i & b])


def _face_contacts(pos, mat, gsize, size, support):
    """Candidates of the box's faces (module docstring), box frame; and each face's overlap
    (the height of the geom's deepest point over the face, wherever it projects)."""
    def face(n):
        pts = support(pos, mat, gsize, n)  # (k, 3)
        height = jnp.abs(n) @ size
        dist = pts @ n - height
        # the point's projection inside the face's rectangle: every other coordinate in range
        inside = jnp.all((jnp.abs(pts) <= size) | (jnp.abs(n) > 0.5), axis=-1)
        held = inside & (pos @ n > height)
        p = pts - 0.5 * dist[:, None] * n
        return (jnp.where(held, dist, NO_CONTACT), p, jnp.broadcast_to(-n, pts.shape),
                jnp.min(dist))
    dist, p, normal, overlap = jax.vmap(face)(_FACES)
    return dist.reshape(-1), p.reshape(-1, 3), normal.reshape(-1, 3), overlap


def _collide(geom, box, support, sdf, metric):
    """The pair's ``NCON`` deepest candidates in the world frame; normal from the smooth geom
    (geom 1) to the box (geom 2)."""
    pos = box.mat.T @ (geom.pos - box.pos)
    mat = box.mat.T @ geom.mat
    corners = _CORNERS * box.size
    dc, pc, gc = sdf_contacts(corners, pos, mat, geom.size, sdf)
    pe, inner = edge_points(corners[_EDGES[:, 0]], corners[_EDGES[:, 1]], pos, mat, metric)
    de, pe, ge = sdf_contacts(pe, pos, mat, geom.size, sdf)
    *face, overlap = _face_contacts(pos, mat, geom.size, box.size, support)
    dist, p, n = (jnp.concatenate(x) for x in zip(
        face, (dc, pc, gc), (jnp.where(inner, de, NO_CONTACT), pe, ge)))
    # Moving the geom out through any face by its overlap there separates the two, so no
    # contact is deeper than the least overlap: a candidate deeper than that is none (a
    # cylinder lying on the top face, overhanging a side: its end against that side face, 5 cm
    # "deep"; clamping it to the bound instead made a contact 2 mm deeper than C's).
    dist = jnp.where(dist < jnp.max(overlap), NO_CONTACT, dist)
    _, idx = jax.lax.top_k(-dist, NCON)
    dist, p, n = dist[idx], p[idx], n[idx]
    return dist, p @ box.mat.T + box.pos, jax.vmap(_math.make_frame)(n @ box.mat.T)


@_convex.collider(ncon=NCON)
def ellipsoid_box(e, b):
    """Contacts of an ellipsoid and a box (module docstring)."""
    return _collide(e, b, ellipsoid_support, ellipsoid_sdf, e.size)


@_convex.collider(ncon=NCON)
def cylinder_box(c, b):
    """Contacts of a cylinder and a box (module docstring)."""
    return _collide(c, b, cylinder_support, cylinder_sdf, c.size[jnp.array([0, 0, 1])])


FUNCTIONS = {(GeomType.ELLIPSOID, GeomType.BOX): ellipsoid_box,
             (GeomType.CYLINDER, GeomType.BOX): cylinder_box}
"""Geom-type pairs this module collides, MJX's driver's keys (the lower type first)."""
