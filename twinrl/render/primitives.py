"""Ray-primitive geometry in a geom's local frame: first hits, closest approaches, normals.

Every function broadcasts over leading axes. A ray is ``o + s * r`` with ``r`` *not* normalised
(the renderer scales it so that ``s`` is the depth along the camera axis); sizes are MuJoCo's
``geom_size`` (sphere ``r``; capsule/cylinder ``r, half-length``; box/ellipsoid half-extents;
plane ``half-x, half-y`` with 0 meaning infinite).

``hit_*`` gives the smallest ``s > 0`` where the ray enters the surface (``inf`` if none): the hard
image, which must agree with OpenGL's. ``closest_*`` gives the closest approach of the *ray line*
to the surface as ``(s*, signed distance)``, negative when the ray passes through the solid: the
quantity the soft silhouette (SoftRas, Liu et al. 2019, Sec. 3.2: a sigmoid of the signed distance
to the boundary) blurs, so that a pose moving an edge gets a gradient where the hard image has
none. Where a closed form exists it is used (boxes: nearest edge outside, the crossing of two
faces inside); cylinders and convex meshes minimise their
signed distance function along the ray by golden-section search with the minimiser held constant
(``stop_gradient``): by the envelope theorem the gradient of ``min_s f(s, theta)`` is
``df/dtheta`` at the minimiser, so the search itself need not be differentiated.

Shared arithmetic lives in ``_raymath`` and the polyhedra (boxes, meshes) in ``polyhedra``; their
public functions are importable from here too.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from twinrl.render._raymath import (  # noqa: F401 (re-exported: part of this module's API)
    EPS,
    INF,
    dot,
    first_positive,
    golden_min,
    line_segment,
    max_last,
    min_last,
    prod_last,
    reduce_last,
    safe_div,
    safe_sqrt,
    sum_last,
)
from twinrl.render.polyhedra import (  # noqa: F401 (re-exported)
    box_depth,
    closest_box,
    hit_triangles,
    polyhedral_depth,
)


# ------------------------------------------------------------------ quadrics
def _line_roots(o, r, rad):
    """Parameters ``s`` where the line ``o + s r`` (vectors on the last axis) is at distance
    ``rad`` from the origin, as (near, far, real?).

    Not through the textbook discriminant ``B^2 - A C`` (``B = o.r``, ``C = |o|^2 - rad^2``): for a
    ray from metres away that grazes a centimetre-sized quadric both terms are ~|o|^2 and their
    difference, ~``A (rad^2 - d^2)``, drowns in float32 rounding (a ray missing a 25 mm pole by
    7 um, 3 m away, was a hit). ``A (rad^2 - |l|^2)``, with ``l`` the line's closest point to the
    origin, is the same number computed without the cancellation."""
    A = dot(r, r)
    B = dot(o, r)
    A = jnp.where(A > EPS, A, EPS)
    lc = o - (B / A)[..., None] * r
    disc = A * (rad * rad - dot(lc, lc))
    sq = safe_sqrt(disc)
    return (-B - sq) / A, (-B + sq) / A, disc >= 0


def hit_sphere(o, r, size):
    s0, _, ok = _line_roots(o, r, size[..., 0])
    return jnp.where(ok, first_positive(s0), INF)


def hit_ellipsoid(o, r, size):
    return hit_sphere(o / size, r / size, jnp.ones_like(size))


def _hit_tube(o, r, rad, h):
    """Side of a z-aligned cylinder of radius ``rad``, ``|z| <= h``."""
    s0, _, ok = _line_roots(o[..., :2], r[..., :2], rad)
    z = o[..., 2] + s0 * r[..., 2]
    return jnp.where(ok & (jnp.abs(z) <= h) & (dot(r[..., :2], r[..., :2]) > EPS),
                     first_positive(s0), INF)


def hit_capsule(o, r, size):
    rad, h = size[..., 0], size[..., 1]
    side = _hit_tube(o, r, rad, h)
    ez = jnp.zeros_like(o).at[..., 2].set(1.0)
    top = hit_sphere(o - h[..., None] * ez, r, size)
    bot = hit_sphere(o + h[..., None] * ez, r, size)
    return jnp.minimum(side, jnp.minimum(top, bot))


def hit_cylinder(o, r, size):
    rad, h = size[..., 0], size[..., 1]
    side = _hit_tube(o, r, rad, h)
    caps = INF
    for sign in (1.0, -1.0):
        s = safe_div(sign * h - o[..., 2], r[..., 2])
        p = o + s[..., None] * r
        inside = p[..., 0] ** 2 + p[..., 1] ** 2 <= rad * rad
        caps = jnp.minimum(caps, jnp.where(inside, first_positive(s), INF))
    return jnp.minimum(side, caps)


def hit_box(o, r, size):
    t1 = safe_div(-size - o, r)
    t2 = safe_div(size - o, r)
    tmin = max_last(jnp.minimum(t1, t2))
    tmax = min_last(jnp.maximum(t1, t2))
    return jnp.where((tmin <= tmax) & (tmin > 0), tmin, INF)


def hit_plane(o, r, size):
    """The plane z = 0, seen from its front (+z) side; finite ``|x| <= sx, |y| <= sy`` when its
    sizes are positive (MuJoCo draws a plane of size 0 as infinite)."""
    s = safe_div(-o[..., 2], r[..., 2])
    p = o + s[..., None] * r
    inside = jnp.where(size[..., 0] > 0, jnp.abs(p[..., 0]) <= size[..., 0], True) & jnp.where(
        size[..., 1] > 0, jnp.abs(p[..., 1]) <= size[..., 1], True)
    return jnp.where((o[..., 2] > 0) & (r[..., 2] < 0) & inside & (s > 0), s, INF)


def surface_level(gtype: int, p, size):
    """A function of local points ``p`` (..., 3) that is 0 on the primitive's surface near ``p``,
    with a non-zero gradient there: what ``hit_implicit`` differentiates. Not a distance away
    from the surface: on geoms with edges (cylinder, box) it is the level of the face ``p`` lies
    on (the face nearest ``p``, chosen without gradient), so its gradient at a hit is that face's
    normal exactly (an SDF's kink, smoothed or not, would be off right at the surface)."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    if gtype == 0:
        return z
    if gtype == 2:
        return jnp.sqrt(x * x + y * y + z * z + 1e-30) - size[..., 0]
    if gtype == 3:
        dz = z - jnp.clip(z, -size[..., 1], size[..., 1])
        return jnp.sqrt(x * x + y * y + dz * dz + 1e-30) - size[..., 0]
    if gtype == 4:
        q = p / size
        return jnp.sqrt(dot(q, q) + 1e-30) - 1.0
    if gtype == 5:
        side = jnp.sqrt(x * x + y * y + 1e-30) - size[..., 0]
        cap = jnp.abs(z) - size[..., 1]
        on_side = jax.lax.stop_gradient(jnp.abs(side) <= jnp.abs(cap))
        return jnp.where(on_side, side, cap)
    if gtype == 6:
        f = [jnp.abs(p[..., i]) - size[..., i] for i in range(3)]
        a = [jax.lax.stop_gradient(jnp.abs(fi)) for fi in f]
        k0 = (a[0] <= a[1]) & (a[0] <= a[2])
        k1 = ~k0 & (a[1] <= a[2])
        return jnp.where(k0, f[0], jnp.where(k1, f[1], f[2]))
    raise ValueError(f"no surface level for geom type {gtype}")


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def hit_implicit(gtype: int, o, r, size):
    """``PRIMITIVES[gtype]``'s first hit ``s`` (the same function), differentiated implicitly.

    At the hit the surface's level ``f(o + s r) = 0`` (``surface_level``), so by the implicit
    function theorem ``ds = -(df at fixed s) / (grad f . r)``: one evaluation of ``f`` is
    differentiated instead of every candidate the closed form tries (a capsule's tube and two
    caps, a box's six slabs, a cylinder's side and caps), whose reverse pass was the largest
    single cost of rendering the arm scenes. A custom JVP, so a render without gradient runs the
    closed form alone."""
    return PRIMITIVES[gtype][1](o, r, size)


@hit_implicit.defjvp
def _hit_implicit_jvp(gtype, primals, tangents):
    o, r, size = primals
    s = PRIMITIVES[gtype][1](o, r, size)
    ok = jnp.isfinite(s)
    s0 = jnp.where(ok, s, 0.0)
    ones = jnp.ones_like(s0)
    slope = jax.jvp(lambda s_: surface_level(gtype, o + s_[..., None] * r, size), (s0,),
                    (ones,))[1]
    slope = jnp.where(ok & (jnp.abs(slope) > EPS), slope, -1.0)
    df = jax.jvp(lambda o, r, size: surface_level(gtype, o + s0[..., None] * r, size), primals,
                 tangents)[1]
    return s, jnp.where(ok, -df / slope, 0.0)


# ------------------------------------------------------------------ signed distance functions
def sdf_box(p, size):
    q = jnp.abs(p) - size
    out = jnp.sqrt(sum_last(jnp.maximum(q, 0.0) ** 2) + 1e-20)
    return out + jnp.minimum(max_last(q), 0.0)


def sdf_cylinder(p, size):
    rad, h = size[..., 0], size[..., 1]
    rxy = jnp.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2 + 1e-20)
    q0, q1 = rxy - rad, jnp.abs(p[..., 2]) - h
    return jnp.minimum(jnp.maximum(q0, q1), 0.0) + jnp.sqrt(
        jnp.maximum(q0, 0.0) ** 2 + jnp.maximum(q1, 0.0) ** 2 + 1e-20)


def sdf(gtype: int, p, size):
    """Signed distance of local points to a primitive (ellipsoid: scaled-sphere approximation;
    plane: distance to its rectangle, 0 thickness)."""
    if gtype == 2:
        return jnp.sqrt(dot(p, p) + 1e-20) - size[..., 0]
    if gtype == 3:
        z = jnp.clip(p[..., 2], -size[..., 1], size[..., 1])
        q = p.at[..., 2].add(-z)
        return jnp.sqrt(dot(q, q) + 1e-20) - size[..., 0]
    if gtype == 4:
        q = p / size
        return (jnp.sqrt(dot(q, q) + 1e-20) - 1.0) * min_last(size)
    if gtype == 5:
        return sdf_cylinder(p, size)
    if gtype == 6:
        return sdf_box(p, size)
    if gtype == 0:
        finite = (size[..., 0] > 0) & (size[..., 1] > 0)
        q = jnp.stack([jnp.abs(p[..., 0]) - size[..., 0], jnp.abs(p[..., 1]) - size[..., 1],
                       jnp.zeros_like(p[..., 0])], -1)
        q = jnp.where(finite[..., None], jnp.maximum(q, 0.0), 0.0).at[..., 2].set(p[..., 2])
        return jnp.sqrt(dot(q, q) + 1e-20)
    raise ValueError(f"no SDF for geom type {gtype}")


def _search_bracket(o_, r_, rb):
    """``line_search_sdf``'s interval of ``s``: the ray's stretch across the bounding sphere."""
    rr = dot(r_, r_)
    sc = -dot(o_, r_) / rr
    half = rb / jnp.sqrt(rr) * 1.05 + 1e-6
    return jnp.maximum(sc - half, 1e-6), jnp.maximum(sc + half, 2e-6)


def line_search_sdf(sdf, o, r, size, rbound, iters):
    """(s*, sdf at s*) along the ray for a convex ``sdf`` of a geom of bounding radius
    ``rbound``."""
    o_, r_, size_, rb = (jax.lax.stop_gradient(x) for x in (o, r, size, rbound))
    lo, hi = _search_bracket(o_, r_, rb)
    s = golden_min(lambda s: sdf(o_ + s[..., None] * r_, size_), lo, hi, iters)
    s = jax.lax.stop_gradient(s)
    return s, sdf(o + s[..., None] * r, size)


def closest_sphere(o, r, size, iters=None):
    rr = dot(r, r)
    s = -dot(o, r) / rr
    p = o + s[..., None] * r
    return s, jnp.sqrt(dot(p, p) + 1e-20) - size[..., 0]


def closest_ellipsoid(o, r, size, iters=None):
    # In the frame scaled to the unit sphere the line-centre distance is exact; scale it back by
    # the mean radius (exact for spheres, and zero exactly at the silhouette for any ellipsoid).
    s, d = closest_sphere(o / size, r / size, jnp.ones_like(size))
    return s, d * jnp.mean(size, -1)


def closest_capsule(o, r, size, iters=None):
    rad, h = size[..., 0], size[..., 1]
    ez = jnp.zeros_like(o).at[..., 2].set(1.0) * h[..., None]
    s, d = line_segment(o, r, -ez, ez)
    return s, d - rad


def closest_cylinder(o, r, size, iters=16):
    """The line's deepest point in, or nearest approach to, a cylinder: ``line_search_sdf``,
    with the derivative of the minimum where it sits on one of the SDF's kinks.

    Inside, the SDF is ``max(q0, q1)`` (side ``q0 = |xy| - rad``, cap ``q1 = |z| - h``), and the
    ray's deepest point is often a kink along the ray that stays a kink as the geometry moves:
    where ``q0 = q1`` (in through a cap, out through the side) and, on a thin disc, where the
    ray crosses the mid-plane (``|z|`` at 0). The derivative of such a minimum is neither
    branch's (which one ``max`` or ``abs`` takes at ``s*`` is rounding) but the mix that keeps
    the minimum on the kink (Danskin): ``lam dq0 + (1 - lam) dq1`` with ``lam = q1' / (q1' -
    q0')`` from the pieces' slopes along the ray, and at the mid-plane ``|z|``'s two branches
    half and half, i.e. no derivative through ``z``. Measured on spatula flipping's mount view
    (``twinrl.render.check.gradcheck``): the 1.2 mm-thick pancake's position and size gradients
    were 185 % and 92 % off, the arm's base 57 % and 43 %. The value is unchanged."""
    rb = jnp.sqrt(size[..., 0] ** 2 + size[..., 1] ** 2)
    s, d = line_search_sdf(sdf_cylinder, o, r, size, rb, iters)
    sg = jax.lax.stop_gradient
    rad, h = size[..., 0], size[..., 1]
    p = o + s[..., None] * r
    ps, rs = sg(p), sg(r)
    # the golden section's last bracket, in s: a kink within it is where the minimum sits
    lo, hi = _search_bracket(sg(o), rs, sg(rb))
    width = (hi - lo) * 0.6180339887498949 ** iters
    z_kink = jnp.abs(ps[..., 2]) <= jnp.abs(rs[..., 2]) * width
    rxy = jnp.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2 + 1e-20)
    q0 = rxy - rad
    q1 = jnp.where(z_kink, sg(jnp.abs(p[..., 2])), jnp.abs(p[..., 2])) - h
    d0 = (ps[..., 0] * rs[..., 0] + ps[..., 1] * rs[..., 1]) / sg(rxy)
    d1 = jnp.where(z_kink, 0.0, jnp.sign(ps[..., 2]) * rs[..., 2])  # the slopes along the ray
    q0s, q1s = sg(q0), sg(q1)
    inside = jnp.maximum(q0s, q1s) < 0
    kink = (d0 * d1 < 0) & (jnp.abs(q0s - q1s) <= (jnp.abs(d0) + jnp.abs(d1)) * width)
    lam = sg(safe_div(d1, d1 - d0))
    g = jnp.where(kink, lam * q0 + (1.0 - lam) * q1, jnp.where(q1s > q0s, q1, q0))
    # Outside (a ray that misses), ``s`` is also where the renderer puts the surface in depth:
    # its derivative by the implicit function theorem on ``f'(s) = 0`` (one Newton step whose
    # value is 0), ``ds = -d(f') / f''``, where ``f`` (the SDF along the ray) curves there.
    ones = jnp.ones_like(s)
    along = lambda t, o_, r_, size_: jax.jvp(
        lambda u: sdf_cylinder(o_ + u[..., None] * r_, size_), (t,), (ones,))[1]
    curve = jax.jvp(lambda t: along(t, sg(o), rs, sg(size)), (s,), (ones,))[1]
    step = -along(s, o, r, size) / jnp.where(curve > EPS, sg(curve), 1.0)
    s_out = jnp.where(~inside & (curve > EPS), s + step - sg(step), s)
    return s_out, jnp.where(inside, sg(d) + g - sg(g), d)


def closest_plane(o, r, size, iters=None):
    """Signed distance, within the plane, of the ray's crossing to the rectangle's border."""
    s = safe_div(-o[..., 2], r[..., 2])
    p = o + s[..., None] * r
    front = (o[..., 2] > 0) & (r[..., 2] < 0)
    qx = jnp.abs(p[..., 0]) - size[..., 0]
    qy = jnp.abs(p[..., 1]) - size[..., 1]
    finite = (size[..., 0] > 0) & (size[..., 1] > 0)
    q = jnp.stack([qx, qy], -1)
    d = jnp.minimum(jnp.maximum(qx, qy), 0.0) + jnp.sqrt(
        jnp.maximum(qx, 0.0) ** 2 + jnp.maximum(qy, 0.0) ** 2 + 1e-20)
    d = jnp.where(finite, d, -1e3)
    return jnp.where(front, s, INF), jnp.where(front, d, 1e3)


# ------------------------------------------------------------------ normals (local frame)
# Unnormalised outward normals. ``tn`` (metres) softens the choice of face on geoms with edges
# (box, cylinder): each face's normal is weighted by softmax(-distance to that face / tn), so a
# pixel's shade moves continuously across an edge (hard argmin when ``tn`` is None). Without it the
# soft image would still jump where a pixel crosses from a box's top to its side.
def normal_sphere(p, size, tn=None):
    return p


def normal_ellipsoid(p, size, tn=None):
    return p / (size * size)


def normal_capsule(p, size, tn=None):
    z = jnp.clip(p[..., 2], -size[..., 1], size[..., 1])
    return p.at[..., 2].add(-z)


def _pick(dists, normals, tn):
    """Normal of the nearest face (hard) or the softmin-weighted blend of all faces' normals."""
    if tn is None:
        k = jnp.argmin(dists, -1)
        return jnp.take_along_axis(normals, k[..., None, None], -2)[..., 0, :]
    w = jax.nn.softmax(-dists / tn[..., None], -1)
    return jnp.sum(w[..., None] * normals, -2)


def normal_cylinder(p, size, tn=None):
    rad, h = size[..., 0], size[..., 1]
    rxy = jnp.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2 + 1e-20)
    dr = jnp.abs(rxy - rad)
    dz = jnp.abs(jnp.abs(p[..., 2]) - h)
    if tn is None:
        w_cap = (dz < dr).astype(p.dtype)
    else:  # softmin of two: a sigmoid
        w_cap = jax.nn.sigmoid((dr - dz) / tn)
    # side normal (x, y, 0) / rxy, cap normal (0, 0, +-1), blended: no (..., 2, 3) stack
    side = (1.0 - w_cap) / rxy
    return jnp.stack([side * p[..., 0], side * p[..., 1],
                      w_cap * jnp.where(p[..., 2] >= 0, 1.0, -1.0).astype(p.dtype)], -1)


def normal_box(p, size, tn=None):
    """Face k's normal is ``e_k sign(p_k)``, so the blend is ``w_k sign(p_k)`` per component:
    the softmin weights themselves, written out over the three faces (no (..., 3, 3) blend)."""
    d = [jnp.abs(jnp.abs(p[..., i]) - size[..., i]) for i in range(3)]
    if tn is None:
        k0 = (d[0] <= d[1]) & (d[0] <= d[2])
        k1 = ~k0 & (d[1] <= d[2])
        w = [k0, k1, ~k0 & ~k1]
        w = [x.astype(p.dtype) for x in w]
    else:
        lo = jnp.minimum(jnp.minimum(d[0], d[1]), d[2])
        e = [jnp.exp((lo - x) / tn) for x in d]
        tot = e[0] + e[1] + e[2]
        w = [x / tot for x in e]
    return jnp.stack([w[i] * jnp.where(p[..., i] >= 0, 1.0, -1.0).astype(p.dtype)
                      for i in range(3)], -1)


def normal_plane(p, size, tn=None):
    return jnp.zeros_like(p).at[..., 2].set(1.0)


def rbound(gtype: int, size):
    """Bounding radius of a primitive from its size (for search brackets and culling)."""
    if gtype == 2:
        return size[..., 0]
    if gtype == 3:
        return size[..., 0] + size[..., 1]
    if gtype in (4, 6):
        return jnp.sqrt(dot(size, size))
    if gtype == 5:
        return jnp.sqrt(size[..., 0] ** 2 + size[..., 1] ** 2)
    raise ValueError(gtype)


PRIMITIVES = {
    # mjtGeom: (name, hit, closest, normal)
    0: ("plane", hit_plane, closest_plane, normal_plane),
    2: ("sphere", hit_sphere, closest_sphere, normal_sphere),
    3: ("capsule", hit_capsule, closest_capsule, normal_capsule),
    4: ("ellipsoid", hit_ellipsoid, closest_ellipsoid, normal_ellipsoid),
    5: ("cylinder", hit_cylinder, closest_cylinder, normal_cylinder),
    6: ("box", hit_box, closest_box, normal_box),
}
GEOM_NAMES = {0: "plane", 1: "hfield", 2: "sphere", 3: "capsule", 4: "ellipsoid",
              5: "cylinder", 6: "box", 7: "mesh", 8: "sdf"}
