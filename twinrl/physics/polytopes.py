"""Contacts MJX 3.17 lacks between an ellipsoid or a cylinder and a box or a convex mesh.

MJX (pinned mujoco-mjx 3.17.0) has no collision function for an ellipsoid or a cylinder against
a box or a convex mesh (its SDF search covers the smooth pairs, its SAT the polytopes);
``mjx.put_model`` refuses such a model ("no collision function for ellipsoid 'tail2' x box
'torso_massive'"). MuJoCo C collides them with its convex penetration test (GJK/EPA), one
contact, whose normal ``mjc_fixNormal`` then sets to the smooth geom's surface normal. This
module collides them the way ``twinrl.physics.hfield`` collides a height field -- the
polytope's surface in place of the field's, with the same candidates (``_shapes``), in the
polytope's frame (MJX's ``ConvexInfo``: vertices, faces as padded polygons, face normals, edges):

- face contacts: for each face whose plane the smooth geom's centre is outside of, the geom's
  support points along the face's inward normal (an ellipsoid's deepest point; a cylinder's rim
  points, a tripod per cap); a point counts where the face's polygon holds its projection.
  Distance: the point's height over the face; normal: the face's.
- vertex contacts: each vertex (a box's 8 corners) against the geom's SDF.
- edge contacts: each edge at its point closest to the geom's centre in the geom's
  proportions, against the SDF.

No contact is deeper than the least of the faces' overlaps (moving the geom out through a face
by its overlap there separates the two); a candidate deeper than that is dropped. The ``NCON``
deepest are the pair's contacts: one where C makes its one (the deepest), more where a flat
face of the geom rests on a face (a cylinder's end: its rim's tripod), so that it rests as on
a plane instead of rocking on one point. Differentiable as ``hfield`` (finite first and second
derivatives; which face holds a point and which candidates are the deepest are discrete
choices: kinks).

Agreement with MuJoCo C (``tests/physics/test_polytopes.py``, placed 2 mm deep): on a face, an
edge or a corner of a box, and on a convex mesh (a wedge), the deepest distance within 1e-6 m
and positions within 2.5e-4 m; normals within 1e-4 degree on a face, 2.1 degrees on an edge or
a corner (C's is the geom's at the midpoint of the penetration, an ellipsoid's by ray
projection; ours the SDF's gradient at the polytope's point). Dropped onto a box landing on a
plane (0.3 s, the box's plane contacts as C makes them: ``contacts="mujoco"``), or onto a
wedge's slope, sliding, positions stay within 0.4 mm of C's.

Not covered: a geom whose centre is inside the polytope (deeper than its own half-size: no face
candidate); a flat cylinder overhanging an edge, tilted, where neither C (1.9 mm along the
face, for a part inside the box 3.8 cm wide and 1.8 cm high) nor the edge's point here (11 mm)
is the least translation that separates them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from mujoco.mjx._src import collision_convex as _convex
from mujoco.mjx._src import math as _math
from mujoco.mjx._src.types import GeomType

from twinrl.physics._shapes import (NO_CONTACT, cylinder_sdf, cylinder_support, edge_points,
                                    ellipsoid_sdf, ellipsoid_support, sdf_contacts)

__all__ = ["ellipsoid_polytope", "cylinder_polytope", "FUNCTIONS", "NCON"]

NCON = 4
"""Contacts per pair (the deepest of the candidates)."""


def _face_contacts(pos, mat, gsize, poly, support):
    """Candidates of the polytope's faces (module docstring), its frame; and each face's
    overlap (the height of the geom's deepest point over the face, wherever it projects)."""
    def face(n, f):  # outward normal, polygon (P, 3) (a vertex repeated to pad it)
        pts = support(pos, mat, gsize, n)  # (k, 3)
        dist = (pts - f[0]) @ n
        # the point's projection inside the convex polygon: on one side of each of its edges
        side = jnp.cross(jnp.roll(f, -1, axis=0) - f, pts[:, None, :] - f) @ n  # (k, P)
        inside = jnp.all(side >= 0.0, axis=-1) | jnp.all(side <= 0.0, axis=-1)
        held = inside & ((pos - f[0]) @ n > 0.0)
        p = pts - 0.5 * dist[:, None] * n
        return (jnp.where(held, dist, NO_CONTACT), p, jnp.broadcast_to(-n, pts.shape),
                jnp.min(dist))
    dist, p, normal, overlap = jax.vmap(face)(poly.face_normal, poly.face)
    return dist.reshape(-1), p.reshape(-1, 3), normal.reshape(-1, 3), overlap


def _collide(geom, poly, support, sdf, metric):
    """The pair's ``NCON`` deepest candidates in the world frame; normal from the smooth geom
    (geom 1) to the polytope (geom 2)."""
    pos = poly.mat.T @ (geom.pos - poly.pos)
    mat = poly.mat.T @ geom.mat
    dv, pv, gv = sdf_contacts(poly.vert, pos, mat, geom.size, sdf)
    a, b = poly.vert[poly.edge[:, 0]], poly.vert[poly.edge[:, 1]]
    pe, inner = edge_points(a, b, pos, mat, metric)
    de, pe, ge = sdf_contacts(pe, pos, mat, geom.size, sdf)
    *face, overlap = _face_contacts(pos, mat, geom.size, poly, support)
    dist, p, n = (jnp.concatenate(x) for x in zip(
        face, (dv, pv, gv), (jnp.where(inner, de, NO_CONTACT), pe, ge)))
    # Moving the geom out through any face by its overlap there separates the two, so no
    # contact is deeper than the least overlap: a candidate deeper than that is none (a
    # cylinder lying on the top face, overhanging a side: its end against that side face, 5 cm
    # "deep"; clamping it to the bound instead made a contact 2 mm deeper than C's).
    dist = jnp.where(dist < jnp.max(overlap), NO_CONTACT, dist)
    _, idx = jax.lax.top_k(-dist, NCON)
    dist, p, n = dist[idx], p[idx], n[idx]
    return dist, p @ poly.mat.T + poly.pos, jax.vmap(_math.make_frame)(n @ poly.mat.T)


@_convex.collider(ncon=NCON)
def ellipsoid_polytope(e, p):
    """Contacts of an ellipsoid and a box or a convex mesh (module docstring)."""
    return _collide(e, p, ellipsoid_support, ellipsoid_sdf, e.size)


@_convex.collider(ncon=NCON)
def cylinder_polytope(c, p):
    """Contacts of a cylinder and a box or a convex mesh (module docstring)."""
    return _collide(c, p, cylinder_support, cylinder_sdf, c.size[jnp.array([0, 0, 1])])


FUNCTIONS = {(GeomType.ELLIPSOID, GeomType.BOX): ellipsoid_polytope,
             (GeomType.CYLINDER, GeomType.BOX): cylinder_polytope,
             (GeomType.ELLIPSOID, GeomType.MESH): ellipsoid_polytope,
             (GeomType.CYLINDER, GeomType.MESH): cylinder_polytope}
"""Geom-type pairs this module collides, MJX's driver's keys (the lower type first)."""
