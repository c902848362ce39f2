"""The JAX renderer: one image (RGB, depth, segmentation, per-geom weights) of a scene, hard or
soft, as an array program. It is the reference the C++ kernel (``kernel``) reproduces, and what
forward-mode and second derivatives go through.

Per pixel: every surface's hit (and, soft, its coverage ``sigmoid(-d / tau)`` from the signed
distance ``d`` in pixels), the ``layers`` surfaces that show most, composited front to back with a
smooth depth order (``gamma``), shaded, and shadowed from the surface that shows most.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.render import primitives as prim
from twinrl.render.camera import Camera
from twinrl.render.cast import cast_mesh, cast_prim, group_params, mesh_normals, select
from twinrl.render.scene import MESH, Geoms, Images
from twinrl.render.shading import geom_albedo, light_dir, shade, unoccluded


def negligible_coverage(dtype) -> float:
    """The coverage below which a surface counts as covering nothing when the layers are chosen:
    sigmoid(-18) ~ 1.5e-8 in float32 (a quarter of its resolution at 1), sigmoid(-30) ~ 9.4e-14
    in float64. Such a surface ranks below every other (it cannot take a hidden surface's place),
    and the C++ kernel neither searches nor differentiates one whose rays all pass that far from
    its silhouette (``twinrl.render.native``)."""
    return 9.357622968840175e-14 if jnp.dtype(dtype) == jnp.float64 else 1.5229979744712629e-08


def render_jax(R, camera: Camera, geoms: Geoms, tau, gamma) -> Images:
    """The image of ``geoms`` seen from ``camera`` (one camera, one scene), drawn by JAX;
    ``tau`` 0 (a Python number): the hard image."""
    soft = not (isinstance(tau, (int, float)) and tau == 0)
    H, W, G = camera.height, camera.width, R.ngeom
    o, r = camera.rays()
    r = r.reshape(-1, 3)
    P = r.shape[0]
    xpos, xmat, size, rgba = select(R, geoms)
    forward = -camera.xmat[:, 2]
    pix = camera.pixel_size()
    albedo = geom_albedo(R, rgba)
    # specular, shininess, emission: constants, kept apart from the albedo so that the
    # reverse pass does not differentiate the shading with respect to them
    mat = np.stack([R.specular, R.shininess, R.emission], -1)
    # how far from a geom's bounding sphere a ray may pass and still be tested against it:
    # the soft silhouette's band (coverage sigmoid(-d / tau) < 1e-6 beyond 14 tau pixels)
    band = (15.0 * tau + 2.0) if soft else 2.0
    reach = jnp.broadcast_to(band * pix, (P,))
    ntau = jnp.broadcast_to(tau * pix, (P,)) if soft else None
    parts = []  # per group: s_hit, s_near, dist, normal, shading inputs, renderer index
    for t, idx in R.groups():
        if t == MESH:
            out = cast_mesh(R, o, r, geoms, xpos, xmat, idx, soft, R.iters, ntau)
            ex, gid = albedo[idx], jnp.asarray(idx, jnp.int32)
            mt = jnp.asarray(mat[idx], albedo.dtype)
            if not soft:
                out = (out[0], mesh_normals(R, o, r, out[0], geoms, xpos, xmat, idx))
        else:
            gx, gm, gs, ex, gid, mt, near = group_params(R, 
                t, idx, o, r, xpos, xmat, size, albedo, reach, R.near, mat)
            out = cast_prim(R, t, o, r, gx, gm, gs, soft, R.iters, ntau,
                                  hard_normals=not soft)
            if soft and near is not None:  # a pick beyond the band covers nothing
                out = (out[0], out[1], jnp.where(near, out[2], 1e6), *out[3:])
        parts.append((*out, ex, mt, gid))
    if any(R.culled(t, idx) for t, idx in R.groups()):
        # per-pixel geoms somewhere: every group's shading inputs per pixel
        parts = [(*q[:-3], jnp.broadcast_to(q[-3], (P, q[0].shape[-1], 4)),
                  jnp.broadcast_to(q[-2], (P, q[0].shape[-1], 3)),
                  jnp.broadcast_to(q[-1], (P, q[0].shape[-1]))) for q in parts]
    # (else the albedo, materials and indices stay one row per geom, broadcast where used:
    # the reverse pass then reduces the albedo's cotangent once per use, not a (P, S, 4))

    def cat(j, ax=-1):
        xs = [q[j] for q in parts]
        if xs[0].ndim == 1 or (ax == -2 and xs[0].ndim == 2):  # per geom, not per pixel
            return jnp.concatenate(xs, 0)
        return jnp.concatenate(xs, ax)
    if soft:
        s_hit, s_n, dist, n = cat(0), cat(1), cat(2), cat(3, -2)
        alb, mt, gid = cat(4, -2), cat(5, -2), cat(6)
    else:
        s_hit, n, alb, mt, gid = cat(0), cat(1, -2), cat(2, -2), cat(3, -2), cat(4)
    S = s_hit.shape[-1]
    s_hit = jnp.where((s_hit >= R.near) & (s_hit <= R.far), s_hit, jnp.inf)
    hit = jnp.isfinite(s_hit)
    first = jnp.argmin(s_hit, -1)
    any_hit = jnp.any(hit, -1)
    g_first = (gid[first] if gid.ndim == 1
               else jnp.take_along_axis(gid, first[:, None], -1)[:, 0])
    seg = jnp.where(any_hit, jnp.asarray(R.geom_ids, jnp.int32)[g_first], -1).reshape(H, W)
    body = jnp.where(any_hit, jnp.asarray(R.bodies)[g_first], -1).reshape(H, W)
    if not soft:
        s_n = jnp.where(hit, s_hit, R.far)
        cover = hit.astype(r.dtype)
    else:
        d_px = dist / (jnp.maximum(s_n, R.near) * pix)
        cover = jax.nn.sigmoid(-d_px / tau) * ((s_n >= R.near) & (s_n <= R.far))
    z = s_n
    p = o + s_n[..., None] * r[:, None, :]
    oh = None
    if S > R.layers:
        # composite (its cost grows with the square of the surfaces) and shade only each
        # pixel's `layers` most covering surfaces among those not hidden: behind the nearest
        # solid one (coverage > 0.999) by more than 10 gamma, a surface's weight is < 1e-3 of
        # its coverage. Ties (hard image: all hits) go to the nearest. A surface whose
        # coverage the dtype cannot resolve ranks below every other (negligible_coverage).
        a_, z_ = jax.lax.stop_gradient(cover), jax.lax.stop_gradient(z)
        solid = jnp.min(jnp.where(a_ > 0.999, z_, jnp.inf), -1, keepdims=True)
        shown = z_ <= solid + (10.0 * gamma if soft else 0.0)
        key = jnp.where(shown, a_ - 1e-6 * z_ / R.far, -1.0 - z_ / R.far)
        key = jnp.where(a_ >= negligible_coverage(r.dtype), key, -3.0)
        lay = jax.lax.top_k(key, R.layers)[1]  # (P, L)
        oh = (lay[..., None] == jnp.arange(S)).astype(r.dtype)  # (P, L, S)

        def pick(x):
            if x.shape[0] != P:  # one row per slot: a product with the one-hot rows
                return jnp.einsum("pls,s...->pl...", oh, x.astype(r.dtype))
            return jnp.take_along_axis(x, lay.reshape(lay.shape + (1,) * (x.ndim - 2)), 1)

        cover, z, p, n, alb, mt = (pick(x) for x in (cover, z, p, n, alb, mt))
        gid = (jnp.take_along_axis(gid, lay, 1) if gid.shape[0] == P
               else jnp.asarray(gid)[lay])
        S = R.layers
    alpha = alb[..., 3]
    if not soft:
        ahead = (z[..., None, :] < z[..., :, None])  # [g, k]: k in front of g
    else:
        ahead = jax.nn.sigmoid((z[..., :, None] - z[..., None, :]) / gamma)
    offdiag = ~np.eye(S, dtype=bool)

    def composite(a):
        # w_g = a_g prod_{k != g} (1 - a_k [k in front of g]); background: prod_k (1 - a_k)
        occl = jnp.where(offdiag, 1.0 - a[..., None, :] * ahead, 1.0)
        w = a * prim.prod_last(occl)
        bg = prim.prod_last(1.0 - a)
        tot = prim.sum_last(w) + bg
        tot = jnp.where(tot > 0, tot, 1.0)
        return w / tot[..., None], bg / tot

    w, bg = composite(cover)
    lit = {}
    if R.shadows and np.any(R.lights["castshadow"]):
        # one shadow ray per pixel, from the surface that shows most there (the hard image's
        # hit): the shadow of every geom's point at that pixel
        win = jnp.argmax(jax.lax.stop_gradient(w), -1)
        pw = jnp.take_along_axis(jax.lax.stop_gradient(p), win[:, None, None], -2)[:, 0]
        gw = gid[win] if gid.ndim == 1 else jnp.take_along_axis(gid, win[:, None], -1)[:, 0]
        for i in np.flatnonzero(R.lights["castshadow"]):
            l, dist_l, _ = light_dir(R, int(i), pw)
            lit[int(i)] = unoccluded(R, pw, l, dist_l, gw, geoms)
    col = shade(R, p, n, o, forward, alb, mt, lit)
    w_rgb, bg_rgb = composite(cover * alpha)
    rgb = jnp.sum(w_rgb[..., None] * col, -2)  # black background
    if soft:
        depth = prim.sum_last(w * z) + bg * R.far_depth
    else:
        depth = jnp.where(any_hit, jnp.min(s_hit, -1), R.far_depth)
    if oh is not None:  # back to every slot
        w = jnp.einsum("pl,pls->ps", w, oh)
    return Images(rgb=rgb.astype(r.dtype).reshape(H, W, 3), depth=depth.reshape(H, W),
                  segmentation=seg,
                  body=body, weights=per_geom(R, w, parts).reshape(H, W, G),
                  background=bg.reshape(H, W))


def per_geom(R, w, parts):
    """Slot weights (P, S) back to geoms (P, G), in renderer order."""
    blocks, order, a = [], [], 0
    for (t, idx), q in zip(R.groups(), parts):
        k = q[0].shape[-1]
        wk = w[:, a:a + k]
        a += k
        if R.culled(t, idx):
            oh = (q[-1][..., None] == jnp.asarray(idx)).astype(w.dtype)  # (P, K, n)
            wk = jnp.einsum("pk,pkn->pn", wk, oh)
        blocks.append(wk)
        order.extend(idx)
    out = jnp.concatenate(blocks, -1)
    if order == sorted(order):
        return out
    return out[:, np.argsort(order)]
