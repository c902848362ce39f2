"""Height-field contacts: a sphere, a capsule, a box, a cylinder or an ellipsoid on a height field.

MJX (pinned mujoco-mjx 3.17.0) collides a height field with a sphere, a capsule, a box or a
convex mesh (``collision_convex.hfield_*``: the geom against each triangular prism of a static
sub-grid, 4 contacts kept among those within 1 mm of the deepest); a cylinder or an ellipsoid
on a height field has no function there, and ``mjx.put_model`` refuses the model. This module
collides all five primitives, differentiable, with MuJoCo C's contacts as the reference for the
forward; ``twinrl.physics.collision`` uses it for these pairs (MJX's mesh function stays).
MJX's own sphere, capsule and box functions differentiate to finite values, but wrong ones: on a
scene of the three landing on the test field and sliding down it
(``tests/physics/foreign/hfield_primitives.xml``, float64, 30 steps) ``twinrl gradcheck`` failed
16 of 103 entries (relative error up to 1.5) and resolved 38; with these functions it fails none
(largest relative error 7e-6) and resolves 73.

MuJoCo C (``mjc_ConvexHField``) runs a convex penetration test (GJK/EPA) of the geom against
every prism under its bounding box -- each grid cell is two triangles, each the top of a prism
down to the field's base -- one contact per penetrated prism (up to ``mjMAXCONPAIR``), then sets
the normal of a smooth geom to its surface normal at the contact (``mjc_fixNormal``). A prism
penetrated through its top face gives the deepest point of the geom along the face's normal;
one poked by a ridge gives a contact about the poking vertex or edge. The same three kinds
here, in a fixed-size form for JAX, over the static sub-grid MJX's driver sizes from the geom's
bounding radius and the grid step (``FunctionKey.subgrid_size``):

- face contacts: for each triangle, the geom's deepest points along the triangle's normal (its
  support points: a sphere's one, a capsule's end spheres' two, a box's corners; an ellipsoid's
  one; a cylinder: the deepest point of each cap's rim and the two at +-120 degrees on that
  rim, a tripod that keeps a cylinder standing on its end stable, as MJX's ``plane_cylinder``).
  A point counts for the triangle whose footprint (its x-y projection) holds it -- the cells
  and their two triangles partition the plane, so each point counts once. Distance: the point's
  height over the triangle's plane; normal: the triangle's; position: halfway into the
  penetration.
- vertex contacts: each grid vertex against the geom's SDF (``_shapes``): distance the SDF,
  normal minus its gradient (the geom's surface normal, as C sets it).
- edge contacts: each cell's three edges (along x, along y, the diagonal) at the edge's point
  closest to the geom's centre in the geom's own proportions (local coordinates divided by its
  half-sizes), then as a vertex. Without them a cylinder landing flat across a ridge edge sank
  7 mm into it, and MuJoCo C's 6 mm contact there was missing.

Of these, the ``NCON`` deepest (``lax.top_k`` on the distance) are the pair's contacts (MJX's
driver sizes a height-field pair's contacts from its table's 4, which this keeps). Four is
enough for a resting geom: at most three points support it (a cylinder on its end: the rim's
tripod; on its side: the two ends of its lowest line; a box: its lowest face's corners) and one
more covers the next triangle or edge as it slides across a crease. Contacts not penetrating
stay in the set with their positive distance (inactive beyond the margin, as every MJX contact).

Agreement with MuJoCo C (``tests/physics/test_hfield.py``, states placed 2 mm deep on the test
field): where C's contact is a prism's face (the geom's deepest point inside one triangle's
footprint), distance, position and normal agree within 2e-7 m, 2.5e-4 m and 1e-4 degree (C's
EPA stops at a tolerance on a rounded surface; a box's or a sphere's agree to 1e-16); on a
vertex, the deepest distance and the position agree as closely, the normal within 0.8 degree
(C projects a ray onto an ellipsoid where this takes its SDF's gradient). Elsewhere the two
differ by construction: C makes one contact per penetrated prism (a vertex's repeated in each of
the up to 6 prisms around it), and takes each prism alone, so a corner or rim near a prism's
vertical side escapes sideways by less than its depth under the surface (a box corner 13.6 mm
under the surface got no contact from C, a disc two with horizontal normals; this module gives
the depth under the surface); an edge contact here lies at the point closest to the centre, C's
where the edge pokes deepest. Rolled out together from the same drop (0.3 s, landing and sliding
down the slopes), positions stay within 0.1 mm of C's for an ellipsoid and a sphere, within
7-12 mm for the cylinders, the capsule and the box.

Differentiability: the support points and SDFs have finite first and second derivatives (square
roots guarded at 0); which triangle holds a point, and which candidates are the deepest, are
discrete choices, so a contact crossing a grid line or trading places with another is piecewise
smooth (``twinrl gradcheck`` reports entries whose perturbation switches a choice as kinks).

Cost: the candidates grow with the sub-grid, the cells under the geom's bounding sphere (a
geom 10 grid steps across: ~100 cells, ~1,000 candidates), as MJX's own height-field functions'
prisms do.

Not covered: the field's outer side walls (C's prisms have them: a geom hitting the field from
the side), a convex mesh (MJX's ``hfield_convex`` stays), margin/gap (``mjx.put_model`` refuses
a margin on a height-field pair).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from mujoco.mjx._src import collision_convex as _convex
from mujoco.mjx._src import math as _math
from mujoco.mjx._src.types import GeomType

from twinrl.physics._shapes import (NO_CONTACT, box_sdf, box_support, capsule_sdf,
                                    capsule_support, cylinder_sdf, cylinder_support, edge_points,
                                    ellipsoid_sdf, ellipsoid_support, sdf_contacts, sphere_sdf,
                                    sphere_support)

__all__ = ["hfield_sphere", "hfield_capsule", "hfield_box", "hfield_cylinder", "hfield_ellipsoid",
           "FUNCTIONS", "NCON"]

NCON = 4
"""Contacts per height-field pair (the deepest of the candidates; module docstring)."""


def _sub_grid(h, pos, rbound, subgrid_size):
    """Vertices (nx + 1, ny + 1, 3) of the static sub-grid under a geom at ``pos`` (field
    frame; ``[i, j]``: column ``cmin + i``, row ``rmin + j``), whether each vertex (nx + 1,
    ny + 1) and each cell (nx, ny) lies in the field, and the grid steps."""
    nx, ny = subgrid_size
    dx = 2.0 * h.size[0] / (h.ncol - 1)
    dy = 2.0 * h.size[1] / (h.nrow - 1)
    cmin = jnp.floor((pos[0] - rbound + h.size[0]) / dx).astype(jnp.int32)
    rmin = jnp.floor((pos[1] - rbound + h.size[1]) / dy).astype(jnp.int32)
    c = cmin + jnp.arange(nx + 1)
    r = rmin + jnp.arange(ny + 1)
    cc, rr = jnp.meshgrid(c, r, indexing="ij")
    z = h.data[jnp.clip(cc, 0, h.ncol - 1), jnp.clip(rr, 0, h.nrow - 1)] * h.size[2]
    vert = jnp.stack([dx * cc - h.size[0], dy * rr - h.size[1], z], axis=-1)
    vert_in = (cc >= 0) & (cc <= h.ncol - 1) & (rr >= 0) & (rr <= h.nrow - 1)
    cell_in = ((cc >= 0) & (cc <= h.ncol - 2) & (rr >= 0) & (rr <= h.nrow - 2))[:nx, :ny]
    return vert, vert_in, cell_in, dx, dy


def _face_contacts(vert, cell_in, dx, dy, support):
    """Candidates of every triangle of the sub-grid: ``support(n)`` points (k, 3) of the geom
    along each triangle's normal ``n``, kept where the triangle's footprint holds them."""
    v00, v10 = vert[:-1, :-1], vert[1:, :-1]
    v01, v11 = vert[:-1, 1:], vert[1:, 1:]
    # the two triangles of a cell, split along its (c, r)-(c+1, r+1) diagonal as MuJoCo does
    n1 = jnp.cross(v11 - v00, v01 - v00)  # (c, r), (c+1, r+1), (c, r+1): above the diagonal
    n2 = jnp.cross(v10 - v00, v11 - v00)  # (c, r), (c+1, r), (c+1, r+1): below it
    n = jnp.stack([n1, n2], axis=2)  # (nx, ny, 2, 3); z = dx dy > 0: never zero
    n = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
    pts = jax.vmap(support)(n.reshape(-1, 3))  # (T, k, 3)
    T, k = pts.shape[:2]
    pts = pts.reshape(n.shape[:3] + (k, 3))
    corner = v00[:, :, None, None, :]
    dist = jnp.sum((pts - corner) * n[:, :, :, None, :], axis=-1)  # (nx, ny, 2, k)
    u = (pts[..., 0] - corner[..., 0]) / dx
    v = (pts[..., 1] - corner[..., 1]) / dy
    in_cell = (u >= 0.0) & (u < 1.0) & (v >= 0.0) & (v < 1.0)
    upper = jnp.array([True, False])[None, None, :, None]
    held = in_cell & jnp.where(upper, u <= v, u > v) & cell_in[:, :, None, None]
    normal = jnp.broadcast_to(n[:, :, :, None, :], pts.shape)
    pos = pts - 0.5 * dist[..., None] * normal
    dist = jnp.where(held, dist, NO_CONTACT)
    return dist.reshape(-1), pos.reshape(-1, 3), normal.reshape(-1, 3)


def _edge_points(vert, cell_in, pos, mat, metric):
    """Points (E, 3) of every grid edge of the sub-grid (each cell's edges along x, along y and
    its diagonal) closest to the geom (``_shapes.edge_points``), and whether each counts."""
    a = jnp.broadcast_to(vert[:-1, :-1], vert[1:, 1:].shape)
    b = jnp.stack([vert[1:, :-1], vert[:-1, 1:], vert[1:, 1:]], axis=2)  # (nx, ny, 3, 3)
    a = jnp.broadcast_to(a[:, :, None, :], b.shape).reshape(-1, 3)
    p, inner = edge_points(a, b.reshape(-1, 3), pos, mat, metric)
    return p, inner & jnp.repeat(cell_in.reshape(-1), 3)


def _point_contacts(points, valid, pos, mat, size, sdf):
    """Candidates of points of the field (vertices, edge points): the geom's SDF there, the
    normal minus the geom's surface normal (the field is geom 1)."""
    dist, p, g = sdf_contacts(points, pos, mat, size, sdf)
    return jnp.where(valid, dist, NO_CONTACT), p, -g


def _collide(h, obj, rbound, subgrid_size, support, sdf, metric):
    """The pair's ``NCON`` deepest candidates in the world frame (module docstring)."""
    pos = h.mat.T @ (obj.pos - h.pos)
    mat = h.mat.T @ obj.mat
    vert, vert_in, cell_in, dx, dy = _sub_grid(h, pos, rbound, subgrid_size)
    face = _face_contacts(vert, cell_in, dx, dy, lambda n: support(pos, mat, obj.size, n))
    vertex = _point_contacts(vert.reshape(-1, 3), vert_in.reshape(-1), pos, mat, obj.size, sdf)
    edge = _point_contacts(*_edge_points(vert, cell_in, pos, mat, metric), pos, mat, obj.size,
                           sdf)
    dist, p, n = (jnp.concatenate(x) for x in zip(face, vertex, edge))
    _, idx = jax.lax.top_k(-dist, NCON)
    dist, p, n = dist[idx], p[idx], n[idx]
    p = p @ h.mat.T + h.pos
    n = n @ h.mat.T
    return dist, p, jax.vmap(_math.make_frame)(n)


@_convex.collider(ncon=NCON)
def hfield_ellipsoid(h, e, subgrid_size):
    """Contacts of a height field and an ellipsoid (module docstring)."""
    return _collide(h, e, jnp.max(e.size), subgrid_size, ellipsoid_support, ellipsoid_sdf,
                    e.size)


@_convex.collider(ncon=NCON)
def hfield_cylinder(h, c, subgrid_size):
    """Contacts of a height field and a cylinder (module docstring)."""
    rbound = jnp.sqrt(c.size[0] ** 2 + c.size[1] ** 2)
    return _collide(h, c, rbound, subgrid_size, cylinder_support, cylinder_sdf,
                    c.size[jnp.array([0, 0, 1])])


@_convex.collider(ncon=NCON)
def hfield_sphere(h, s, subgrid_size):
    """Contacts of a height field and a sphere (module docstring)."""
    return _collide(h, s, s.size[0], subgrid_size, sphere_support, sphere_sdf,
                    s.size[jnp.array([0, 0, 0])])


@_convex.collider(ncon=NCON)
def hfield_capsule(h, c, subgrid_size):
    """Contacts of a height field and a capsule (module docstring)."""
    return _collide(h, c, c.size[0] + c.size[1], subgrid_size, capsule_support, capsule_sdf,
                    jnp.array([1.0, 1.0, 0.0]) * c.size[0] + jnp.array([0.0, 0.0, 1.0]) * (
                        c.size[0] + c.size[1]))


@_convex.collider(ncon=NCON)
def hfield_box(h, b, subgrid_size):
    """Contacts of a height field and a box (module docstring)."""
    return _collide(h, b, jnp.linalg.norm(b.size), subgrid_size, box_support, box_sdf,
                    b.size)


FUNCTIONS = {(GeomType.HFIELD, GeomType.SPHERE): hfield_sphere,
             (GeomType.HFIELD, GeomType.CAPSULE): hfield_capsule,
             (GeomType.HFIELD, GeomType.BOX): hfield_box,
             (GeomType.HFIELD, GeomType.ELLIPSOID): hfield_ellipsoid,
             (GeomType.HFIELD, GeomType.CYLINDER): hfield_cylinder}
"""Geom-type pairs this module collides, MJX's driver's keys (height field first)."""
