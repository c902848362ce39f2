"""The loss terms of a visual fit, and the metric residuals of its geometric refinement.

The Adam stage minimises ``frame_loss`` (a weighted sum of RGB, soft-IoU, depth, point-to-model
and Sinkhorn-EMD terms per frame; ``pixel_subset`` fixes the EMD's pixels). The
Levenberg-Marquardt refinement that follows works on metric residuals: each real depth point's
signed distance to its geom (``surface_residuals``), how deep the rays of pixels a geom does not
own pass inside it (``free_space_residuals``), a weak soft-silhouette tie-break
(``silhouette_residuals``) and a resting object's lowest point (``lowest_z``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.real2sim.visual.config import VisualConfig
from twinrl.render import Camera, Geoms, Renderer
from twinrl.render.pointcloud import depth_to_points, huber_residual, sinkhorn_emd


def soft_iou(w, m):
    """Soft intersection over union of two masks of weights in [0, 1] (H, W)."""
    inter = jnp.sum(w * m)
    union = jnp.sum(w + m - w * m)
    return inter / jnp.maximum(union, 1e-6)


def frame_loss(R: Renderer, cfg: VisualConfig, cam: Camera, geoms: Geoms, real: dict, tau,
                focus: int | None, pix_idx):
    """Loss terms of one frame. ``focus``: index (renderer order) of the object whose mask and
    point cloud are compared, or a tuple of them (a body's geoms; None: every geom)."""
    im = R.render(cam, geoms, tau=tau, gamma=cfg.gamma)
    rgb_real = real["rgb"].astype(im.rgb.dtype) / 255.0
    care = real["care"].astype(im.rgb.dtype)  # 0 on pixels of ignored geoms
    terms = {"rgb": jnp.sum(care[..., None] * (im.rgb - rgb_real) ** 2)
             / jnp.maximum(3.0 * jnp.sum(care), 1.0)}
    onehot = (real["segmentation"][..., None] == jnp.asarray(R.geom_ids)).astype(im.rgb.dtype)
    onehot = onehot * care[..., None]
    weights = im.weights * care[..., None]
    if focus is None:
        present = jnp.sum(onehot, (0, 1)) + jnp.sum(weights, (0, 1)) > 0
        ious = jax.vmap(soft_iou, in_axes=(-1, -1))(weights, onehot)
        terms["iou"] = 1.0 - jnp.sum(ious * present) / jnp.maximum(jnp.sum(present), 1)
        real_w = (real["segmentation"] >= 0).astype(im.rgb.dtype) * care
        sim_w = (1.0 - im.background) * care
    elif isinstance(focus, tuple):  # several geoms (a rigid body's): their IoUs averaged
        idx = np.asarray(focus)
        w_f, o_f = weights[..., idx], onehot[..., idx]
        present = jnp.sum(o_f, (0, 1)) + jnp.sum(w_f, (0, 1)) > 0
        ious = jax.vmap(soft_iou, in_axes=(-1, -1))(w_f, o_f)
        terms["iou"] = 1.0 - jnp.sum(ious * present) / jnp.maximum(jnp.sum(present), 1)
        real_w, sim_w = jnp.sum(o_f, -1), jnp.sum(w_f, -1)
    else:
        terms["iou"] = 1.0 - soft_iou(weights[..., focus], onehot[..., focus])
        real_w = onehot[..., focus]
        sim_w = weights[..., focus]
    seen = (real["segmentation"] >= 0).astype(im.rgb.dtype) * care
    terms["depth"] = jnp.sum(seen * jnp.abs(im.depth - real["depth"])) / jnp.maximum(
        jnp.sum(seen), 1.0)
    pts, _ = depth_to_points(cam, real["depth"])
    sd = R.sdf(pts, geoms)  # (H*W, G)
    oh = onehot.reshape(-1, onehot.shape[-1])
    if focus is not None:
        idx = np.asarray(focus if isinstance(focus, tuple) else (focus,))
        oh, sd = oh[:, idx], sd[:, idx]
    # per geom, then averaged over the geoms seen: small objects count as much as the floor
    per = jnp.sum(oh * sd ** 2, 0) / jnp.maximum(jnp.sum(oh, 0), 1.0)
    terms["surface"] = jnp.sum(per) / jnp.maximum(jnp.sum(jnp.sum(oh, 0) > 0), 1)
    if cfg.w_emd > 0:
        pr, wr = depth_to_points(cam, real["depth"], real_w)
        ps, ws = depth_to_points(cam, im.depth, sim_w)
        terms["emd"] = sinkhorn_emd(pr[pix_idx], ps[pix_idx], wr[pix_idx], ws[pix_idx],
                                    epsilon=cfg.emd_epsilon)
    else:
        terms["emd"] = jnp.zeros(())
    total = (cfg.w_rgb * terms["rgb"] + cfg.w_iou * terms["iou"] + cfg.w_depth * terms["depth"]
             + cfg.w_emd * terms["emd"] + cfg.w_surface * terms["surface"])
    return total, terms


def pixel_subset(frames, n, focus_id, rng):
    """Fixed pixels for the EMD clouds: where the real frames show the object (or any geom),
    grown by a margin so the rendered estimate's points are there too."""
    import scipy.ndimage as ndi

    segs = np.stack([f["segmentation"] for f in frames])
    mask = (segs == focus_id) if focus_id is not None else (segs >= 0)
    mask = ndi.binary_dilation(mask.any(0), iterations=3).ravel()
    cand = np.flatnonzero(mask)
    if cand.size == 0:
        cand = np.arange(mask.size)
    return jnp.asarray(rng.choice(cand, size=min(n, cand.size), replace=cand.size < n))


def surface_residuals(R: Renderer, cfg: VisualConfig, cam: Camera, geoms: Geoms, real: dict,
                       focus: int | None):
    """Signed distance (m, Huber) of each real depth point, unprojected with ``cam``, to the geom
    the real segmentation assigns it (only the ``focus`` geom's points when given, or those of a
    tuple of geoms); weighted so every geom seen counts as much as any other, whatever its pixel
    count. (H*W,)"""
    pts, _ = depth_to_points(cam, real["depth"])
    sd = R.sdf(pts, geoms)
    oh = (real["segmentation"].reshape(-1, 1) == jnp.asarray(R.geom_ids)).astype(sd.dtype)
    oh = oh * real["care"].reshape(-1, 1).astype(sd.dtype)
    if focus is not None:
        idx = np.asarray(focus if isinstance(focus, tuple) else (focus,))
        oh, sd = oh[:, idx], sd[:, idx]
    n = jnp.sum(oh, 0)
    w = oh / jnp.sqrt(jnp.maximum(n, 1.0) * jnp.maximum(jnp.sum(n > 0), 1))
    return jnp.sum(w * huber_residual(jnp.where(oh > 0, sd, 0.0), cfg.huber), -1)


def focus_rays(R: Renderer, cam: Camera, geoms: Geoms, focus: int):
    """Each pixel ray's hit-or-closest-approach depth and signed distance (m) to the ``focus``
    geom. (H*W,) each."""
    o, r = cam.rays()
    _, s_n, dist, _ = R.cast(o, r.reshape(-1, 3), geoms, soft=True)
    return s_n[:, focus], dist[:, focus]


def free_space_residuals(R: Renderer, cfg: VisualConfig, rays, real: dict, focus: int):
    """How deep (m, Huber) the ray of each pixel the real segmentation does *not* give to the
    ``focus`` geom passes inside that geom in front of the real depth: the silhouette, in metres.
    (H*W,)"""
    s_n, dist = rays
    other = real["segmentation"].reshape(-1) != R.geom_ids[focus]
    pen = jnp.where(other & (s_n < real["depth"].reshape(-1)), jnp.maximum(-dist, 0.0), 0.0)
    n = jnp.sum(real["segmentation"] == R.geom_ids[focus])
    return huber_residual(pen, cfg.huber) / jnp.sqrt(jnp.maximum(n, 1.0))


def silhouette_residuals(R: Renderer, cfg: VisualConfig, cam: Camera, rays, real: dict,
                          focus: int):
    """Soft coverage of each unoccluded pixel by the ``focus`` geom (temperature ``tau[1]``
    pixels) minus whether the real segmentation gives it that geom, in metres (times the pixel's
    footprint), times 0.1. Zero-cost placements of an edge span the gap between a labelled and an
    unlabelled pixel centre; this weak term only breaks that tie (towards the gap's middle): with
    full weight it would override the narrower gap that several views' hard constraints leave
    (bench seed 0: 0.7 % -> 3.7 % size error). (H*W,)"""
    s_n, dist = rays
    foot = jnp.maximum(s_n, R.near) * cam.pixel_size()
    cover = jax.nn.sigmoid(-dist / (foot * cfg.tau[1]))
    label = (real["segmentation"].reshape(-1) == R.geom_ids[focus]).astype(cover.dtype)
    # a pixel something else hides (real surface in front of the geom) says nothing of its edge
    seen = (label > 0) | (real["depth"].reshape(-1) >= s_n)
    n = jnp.maximum(jnp.sum(label), 1.0)
    return 0.1 * jnp.where(seen, (cover - label) * jax.lax.stop_gradient(foot), 0.0) / jnp.sqrt(n)


def lowest_z(geoms: Geoms, gid: int, gtype: int):
    """World height of the lowest point of geom ``gid`` (``Geoms`` of one frame)."""
    R, c, s = geoms.xmat[gid], geoms.xpos[gid, 2], geoms.size[gid]
    rz = R[2]  # the world z component of the geom's local axes
    if gtype == 2:  # sphere
        return c - s[0]
    if gtype == 3:  # capsule
        return c - s[0] - jnp.abs(rz[2]) * s[1]
    if gtype == 5:  # cylinder
        return c - jnp.abs(rz[2]) * s[1] - s[0] * jnp.sqrt(jnp.maximum(1 - rz[2] ** 2, 1e-12))
    if gtype == 4:  # ellipsoid
        return c - jnp.sqrt(jnp.sum((rz * s) ** 2))
    if gtype == 6:  # box
        return c - jnp.sum(jnp.abs(rz) * s)
    raise ValueError(f"keep_support: no lowest point for geom type {gtype}; set "
                     "keep_support=False")
