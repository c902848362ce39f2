"""Rays against a renderer's geoms: first hits, closest approaches, signed distances and normals,
and the per-pixel culling that picks which geoms of a crowded type each ray is tested against.

Each function takes the ``Renderer`` ``R`` first (its static structure: geom types, mesh faces,
near/far planes, culling settings) and the ``Geoms`` pytree, and is differentiable in the latter.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.render import primitives as prim
from twinrl.render.scene import MESH, Geoms


def to_local(v, xmat):
    """``v @ xmat`` per geom: ``v`` (..., g, 3); ``xmat`` (g, 3, 3) shared by every ray (a
    batched matrix product) or (..., g, 3, 3) per ray (written out elementwise, so it fuses)."""
    if xmat.ndim == 3:
        return jnp.einsum("...gi,gij->...gj", v, xmat)
    return (v[..., 0:1] * xmat[..., 0, :] + v[..., 1:2] * xmat[..., 1, :]
            + v[..., 2:3] * xmat[..., 2, :])


def to_world(v, xmat):
    """``xmat @ v`` per geom (the inverse of ``to_local``)."""
    if xmat.ndim == 3:
        return jnp.einsum("...gj,gij->...gi", v, xmat)
    return (v[..., 0:1] * xmat[..., :, 0] + v[..., 1:2] * xmat[..., :, 1]
            + v[..., 2:3] * xmat[..., :, 2])


def select(R, geoms: Geoms):
    """The rows of the drawn geoms, in renderer order: ``(xpos, xmat, size, rgba)``;
    ValueError for ``Geoms`` of another model or a batch of scenes (``jax.vmap`` those)."""
    gi = np.asarray(R.geom_ids)
    if geoms.xpos.ndim != 2 or geoms.xpos.shape[-1] != 3 or geoms.xmat.shape[-2:] != (3, 3):
        raise ValueError(f"Geoms.xpos must be (G, 3) and xmat (G, 3, 3); got "
                         f"{geoms.xpos.shape}, {geoms.xmat.shape} (vmap batches of scenes)")
    if geoms.xpos.shape[0] <= gi.max():
        raise ValueError(f"Geoms has {geoms.xpos.shape[0]} geoms; this renderer draws geom "
                         f"{gi.max()}: render with Geoms of the renderer's own model")
    return (geoms.xpos[gi], geoms.xmat[gi], geoms.size[gi], geoms.rgba[gi])


def triangles(R, geoms: Geoms, xpos, xmat):
    """World vertices (T, 3, 3) of every mesh triangle the renderer draws."""
    k = jnp.asarray(R.tri_geom)
    v = geoms.mesh_vert[jnp.asarray(R.tri_vert)]  # (T, 3, 3) local
    return jnp.einsum("tij,tcj->tci", xmat[k], v) + xpos[k][:, None, :]


def cast(R, o, r, geoms: Geoms, *, soft: bool = False, iters: int | None = None,
         normal_tau=None):
    """Intersect rays ``o + s r`` (o (..., 3) or (3,), r (..., 3)) with every drawn geom.

    Returns ``s_hit`` (..., G) (inf: no hit), and with ``soft`` also ``s_near`` (..., G) (the
    hit, else the closest approach), ``dist`` (..., G) signed distance (m) of the ray to the
    geom's boundary and unit world ``normal`` (..., G, 3) at ``o + s_near r``, blended
    across edges over ``normal_tau * s_near`` metres (``normal_tau`` (...,): metres per unit
    depth; None: hard).
    """
    xpos, xmat, size, _ = select(R, geoms)
    iters = R.iters if iters is None else iters
    batch = r.shape[:-1]
    G = R.ngeom
    s_hit = [None] * G
    s_near, dist, normal = [None] * G, [None] * G, [None] * G
    types = np.asarray(R.types)
    for t in sorted(set(R.types)):
        idx = np.flatnonzero(types == t)
        if t == MESH:
            out = cast_mesh(R, o, r, geoms, xpos, xmat, idx, soft, iters, normal_tau)
        else:
            out = cast_prim(R, t, o, r, xpos[idx], xmat[idx], size[idx], soft, iters,
                                  normal_tau)
        for j, g in enumerate(idx):
            s_hit[g] = out[0][..., j]
            if soft:
                s_near[g], dist[g], normal[g] = (out[1][..., j], out[2][..., j],
                                                 out[3][..., j, :])
    s_hit = jnp.stack(s_hit, -1)
    assert s_hit.shape == (*batch, G)
    if not soft:
        return s_hit
    return s_hit, jnp.stack(s_near, -1), jnp.stack(dist, -1), jnp.stack(normal, -2)


def cast_prim(R, t, o, r, xpos, xmat, size, soft, iters, normal_tau=None,
               hard_normals=False, differentiable=True):
    """One primitive type's geoms: ``xpos`` (g, 3), ``xmat`` (g, 3, 3), ``size`` (g, 3) for
    every ray, or (..., g, 3[, 3]) per ray (the geoms culling chose for each pixel).
    ``differentiable=False``: the hits of rays whose gradient nobody takes (shadow rays)."""
    _, hit, closest, normal = prim.PRIMITIVES[t]
    # local frame: p_loc = xmat^T (p - xpos)
    o_l = to_local(o[..., None, :] - xpos, xmat)
    r_l = (jnp.einsum("...i,gij->...gj", r, xmat) if xmat.ndim == 3
           else to_local(r[..., None, :], xmat))
    s_hit = prim.hit_implicit(t, o_l, r_l, size) if differentiable else hit(o_l, r_l, size)
    if not soft:
        if not hard_normals:
            return (s_hit,)
        p = o_l + jnp.where(jnp.isfinite(s_hit), s_hit, R.far)[..., None] * r_l
        n = to_world(normal(p, size), xmat)
        return s_hit, n / jnp.sqrt(prim.dot(n, n) + 1e-20)[..., None]
    s_c, d = closest(o_l, r_l, size, iters)
    s_n = jnp.where(jnp.isfinite(s_hit), s_hit, s_c)
    s_n = jnp.where(jnp.isfinite(s_n), s_n, R.far)
    p = o_l + s_n[..., None] * r_l
    tn = None if normal_tau is None else normal_tau[..., None] * s_n
    n = to_world(normal(p, size, tn), xmat)
    n = n / jnp.sqrt(prim.dot(n, n) + 1e-20)[..., None]
    return s_hit, s_n, d, n


def cast_mesh(R, o, r, geoms, xpos, xmat, idx, soft, iters, normal_tau=None):
    """``cast_prim`` for the mesh geoms ``idx`` (renderer indices): the hits of their triangles
    and, with ``soft``, the closest approach to the convex hull."""
    tri = triangles(R, geoms, xpos, xmat)  # (T, 3, 3) world
    k = np.asarray(R.tri_geom)
    sel = np.stack([k == g for g in idx])  # (Gm, T) which triangles belong to which geom
    s_tri = prim.hit_triangles(o[..., None, :], r[..., None, :], tri[:, 0], tri[:, 1],
                               tri[:, 2])  # (..., T)
    s_hit = jnp.min(jnp.where(sel, s_tri[..., None, :], jnp.inf), -1)  # (..., Gm)
    if not soft:
        return (s_hit,)
    # A convex mesh is the intersection of its faces' half-spaces: max of plane distances.
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    fn = jnp.cross(e1, e2)
    fn = fn / jnp.sqrt(jnp.sum(fn * fn, -1, keepdims=True) + 1e-30)
    off = jnp.sum(fn * tri[:, 0], -1)

    def planes(p):  # p (..., Gm, 3) -> (..., Gm, T)
        return jnp.where(sel, jnp.einsum("...gi,ti->...gt", p, fn) - off, -jnp.inf)

    o_b = jnp.broadcast_to(o[..., None, :], (*r.shape[:-1], len(idx), 3))
    r_b = jnp.broadcast_to(r[..., None, :], (*r.shape[:-1], len(idx), 3))
    cen = xpos[idx]
    corner = jnp.linalg.norm(tri - xpos[k][:, None, :], axis=-1).max(-1)  # (T,)
    rb = jax.lax.stop_gradient(jnp.max(jnp.where(sel, corner, 0.0), -1))  # (Gm,)
    sdf = lambda p, c: jnp.max(planes(p + c), -1)  # noqa: E731 - p relative to the centre
    s_in, _ = prim.line_search_sdf(sdf, o_b - cen, r_b,
                                    jnp.broadcast_to(cen, o_b.shape), rb, iters)
    m_f = jnp.where(sel, jnp.einsum("...gi,ti->...gt", r_b, fn), 0.0)
    c_f = jnp.where(sel, jnp.einsum("...gi,ti->...gt", o_b, fn) - off, -jnp.inf)
    d_in = prim.polyhedral_depth(m_f, c_f, s_in)
    # outside a convex mesh the ray passes closest to one of its edges (exact, differentiable)
    ea = jnp.concatenate([tri[:, 0], tri[:, 1], tri[:, 2]])
    eb = jnp.concatenate([tri[:, 1], tri[:, 2], tri[:, 0]])
    s_e, d_e = prim.line_segment(o_b[..., None, :], r_b[..., None, :], ea, eb)  # (..., Gm, 3T)
    d_e = jnp.where(np.tile(sel, (1, 3)), d_e, jnp.inf)
    k = jnp.argmin(d_e, -1)
    s_out = jnp.take_along_axis(s_e, k[..., None], -1)[..., 0]
    d_out = jnp.take_along_axis(d_e, k[..., None], -1)[..., 0]
    inside = d_in < 0
    s_c, d = jnp.where(inside, s_in, s_out), jnp.where(inside, d_in, d_out)
    s_n = jnp.where(jnp.isfinite(s_hit), s_hit, s_c)
    p = o_b + s_n[..., None] * r_b
    vals = planes(p)
    if normal_tau is None:
        return s_hit, s_n, d, fn[jnp.argmax(vals, -1)]
    w = jax.nn.softmax(vals / (normal_tau[..., None] * s_n)[..., None], -1)
    return s_hit, s_n, d, jnp.einsum("...gt,ti->...gi", w, fn)


def signed_distance(R, points: jax.Array, geoms: Geoms) -> jax.Array:
    """Signed distance (m) of world ``points`` (..., 3) to each drawn geom's surface
    (..., G): exact for sphere, capsule, box, cylinder, plane (|z| inside its rectangle);
    approximate for ellipsoids; a convex mesh's largest face-plane distance."""
    xpos, xmat, size, _ = select(R, geoms)
    types = np.asarray(R.types)
    out = [None] * R.ngeom
    for t in sorted(set(R.types)):
        idx = np.flatnonzero(types == t)
        if t == MESH:
            fn, off, sel = face_planes(R, geoms, xpos, xmat, idx)
            vals = jnp.where(sel, (points @ fn.T - off)[..., None, :], -jnp.inf)
            d = jnp.max(vals, -1)
        else:
            p = jnp.einsum("...gi,gij->...gj", points[..., None, :] - xpos[idx], xmat[idx])
            d = prim.sdf(t, p, size[idx])
        for j, g in enumerate(idx):
            out[g] = d[..., j]
    return jnp.stack(out, -1)


def face_planes(R, geoms, xpos, xmat, idx):
    """Unit normals ``fn`` (T, 3) and offsets ``off`` (T,) of every mesh triangle's plane in
    the world, and ``sel`` (len(idx), T): which triangles belong to each mesh geom in ``idx``
    (a convex mesh's distance is its largest face-plane distance)."""
    tri = triangles(R, geoms, xpos, xmat)
    k = np.asarray(R.tri_geom)
    sel = np.stack([k == g for g in idx])
    fn = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn = fn / jnp.sqrt(jnp.sum(fn * fn, -1, keepdims=True) + 1e-30)
    return fn, jnp.sum(fn * tri[:, 0], -1), sel


def mesh_normals(R, o, r, s_hit, geoms, xpos, xmat, idx):
    """Hard normals of mesh geoms ``idx`` where the rays hit them (the face whose plane the
    hit point lies on). (..., len(idx), 3)"""
    fn, off, sel = face_planes(R, geoms, xpos, xmat, idx)
    p = o + jnp.where(jnp.isfinite(s_hit), s_hit, R.far)[..., None] * r[..., None, :]
    vals = jnp.where(sel, jnp.einsum("...gi,ti->...gt", p, fn) - off, -jnp.inf)
    return fn[jnp.argmax(vals, -1)]


# ------------------------------------------------------------------ culling
def choose(R, t, idx, o, r, xpos, xmat, size, reach, front):
    """The ``per_pixel`` geoms of ``idx`` (one primitive type) each ray is tested against.
    Each geom is bounded by a capsule (a segment along its longest axis; exact for capsules);
    the rays passing through it come first, nearest first, then those passing within
    ``reach`` (..., metres per unit of ``s``; None: 0) of it, closest first (the soft
    silhouette's band); only ``s`` past ``front`` counts. Returns their positions in
    ``idx`` (..., K), as one-hot rows (..., K, n), and whether each is one of those (...,
    K): a pick beyond the band only fills the K places and covers nothing (where the
    pixel has fewer than K geoms near it); no gradient (a geom left out covers nothing
    there)."""
    sg = jax.lax.stop_gradient
    c, m, h, o, r = sg(xpos[idx]), sg(xmat[idx]), sg(size[idx]), sg(o), sg(r)
    if t == 2:  # sphere
        half, rad, axis = jnp.zeros_like(h[:, 0]), h[:, 0], m[:, :, 2]
    elif t in (3, 5):  # capsule, cylinder: along z
        half, rad, axis = h[:, 1], h[:, 0], m[:, :, 2]
    else:  # box, ellipsoid: the longest axis, radius the other two's diagonal
        k = jnp.argmax(h, -1)
        half = jnp.max(h, -1)
        rad = jnp.sqrt(jnp.maximum(jnp.sum(h * h, -1) - half * half, 0.0))
        axis = jnp.sum(m * (k[:, None] == jnp.arange(3))[:, None, :], -1)
    e = half[:, None] * axis
    s_c, dist = prim.line_segment(o[..., None, :], r[..., None, :], c - e, c + e)  # (..., n)
    depth = jnp.maximum(s_c, R.near)
    lim = rad if reach is None else rad + reach[..., None] * depth
    core = dist <= rad * 1.001 + 1e-6
    band = (dist <= lim * 1.001 + 1e-6) & (s_c + half + rad >= front)
    near = core & (s_c + half + rad >= front)
    score = jnp.where(near, 1e6 - s_c, jnp.where(band, -(dist - rad) / depth, -1e9 - dist))
    k = jax.lax.top_k(score, R.per_pixel)[1]
    return (k, (k[..., None] == jnp.arange(len(idx))).astype(r.dtype),
            jnp.take_along_axis(near | band, k, -1))


def group_params(R, t, idx, o, r, xpos, xmat, size, extra, reach, front, const=None):
    """Per group of one type: the geoms' (or, culled, each ray's chosen geoms') ``xpos``,
    ``xmat``, ``size``, ``extra`` (G, E) per-geom columns, renderer indices ``gid`` ((n,)
    static, else (..., K)), the rows of the NumPy table ``const`` (G, C), and (culled)
    whether each choice is near the ray (``choose``; else None)."""
    dt = xpos.dtype
    if not R.culled(t, idx):
        return (xpos[idx], xmat[idx], size[idx], extra[idx], jnp.asarray(idx, jnp.int32),
                None if const is None else jnp.asarray(const[idx], dt), None)
    k, oh, near = choose(R, t, idx, o, r, xpos, xmat, size, reach, front)
    n = len(idx)
    table = jnp.concatenate([xpos[idx], xmat[idx].reshape(n, 9), size[idx], extra[idx]], -1)
    # a one-hot matrix product, not a gather: its reverse pass is another product (a gather's
    # is a scatter, which XLA on CPU runs serially)
    tab = jnp.einsum("...kn,nd->...kd", oh, table)
    return (tab[..., 0:3], tab[..., 3:12].reshape(*tab.shape[:-1], 3, 3), tab[..., 12:15],
            tab[..., 15:], jnp.asarray(idx, jnp.int32)[k],
            None if const is None else oh @ jnp.asarray(const[idx], dt), near)
