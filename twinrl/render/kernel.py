"""The renderer's calls into the C++ kernel (``twinrl.render.native``): the scene and the inputs
packed as the kernel takes them, its image and its reverse pass (the cotangents of the camera and
the geoms), as JAX FFI calls. ``batching.render_batched`` decides when they are used.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.render.camera import Camera
from twinrl.render.cast import select
from twinrl.render.scene import MESH, Geoms, Images
from twinrl.render.shading import geom_albedo


def scene_attrs(R) -> dict | None:
    """The scene as the C++ kernel (``twinrl.render.native``) takes it; None where it does
    not draw it (meshes; more than 64 geoms or surfaces a pixel)."""
    if MESH in R.types or R.ngeom > 64 or R.surfaces() > 64 or R.layers > 64:
        return None
    L, hl = R.lights, R.headlight
    rows = [np.concatenate([[L["type"][i]], L["pos"][i], L["dir"][i], L["ambient"][i],
                            L["diffuse"][i], L["specular"][i],
                            [L["cutoff"][i], L["exponent"][i]], L["attenuation"][i],
                            [float(L["castshadow"][i])]]) for i in range(len(L["type"]))]
    return dict(
        types=np.asarray(R.types, np.int32), gids=np.asarray(R.geom_ids, np.int32),
        bodies=np.asarray(R.bodies, np.int32),
        opts=np.asarray([R.iters, R.per_pixel, R.cull_above, R.layers,
                         int(R.shadows)], np.int32),
        mat=np.stack([R.specular, R.shininess, R.emission], -1).reshape(-1),
        lights=np.concatenate(rows).astype(np.float64) if rows else np.zeros(0),
        headlight=np.concatenate([[float(hl["active"])], hl["ambient"], hl["diffuse"],
                                  hl["specular"]]).astype(np.float64))


def native_target(R, camera: Camera, geoms: Geoms) -> str | None:
    """The C++ kernel's FFI target for this render, or None (JAX draws it)."""
    from twinrl.render import native

    if R.kernel_attrs is None or not native.available():
        return None
    dt = jnp.result_type(camera.pos.dtype, geoms.xpos.dtype)
    return native.TARGETS.get(jnp.dtype(dt).name)


def native_inputs(R, camera: Camera, geoms: Geoms, dt):
    """The kernel's inputs: cam (15,) = position, xmat (row-major), pixel size, principal
    point; geo (G, 19) = xpos, xmat, size, albedo of the renderer's geoms."""
    xpos, xmat, size, rgba = select(R, geoms)
    cx, cy = camera.principal_point()
    cam = jnp.concatenate([camera.pos.astype(dt), camera.xmat.reshape(9).astype(dt),
                           jnp.stack([camera.pixel_size(), cx, cy]).astype(dt)])
    geo = jnp.concatenate([xpos, xmat.reshape(R.ngeom, 9), size, geom_albedo(R, rgba)],
                          -1).astype(dt)
    return cam, geo


def native_call(R, target: str, outs, *args):
    """The FFI call of ``target`` on ``args`` with the scene's attributes (``R.kernel_attrs``)."""
    call = jax.ffi.ffi_call(target, outs, vmap_method="broadcast_all")
    scal = np.asarray([R.near, R.far, R.far_depth], np.float64)
    return call(*args, scal=scal, **R.kernel_attrs)


def render_native(R, camera: Camera, geoms: Geoms, tg, target: str) -> Images:
    """``image.render_jax``'s values from the C++ kernel (``tg``: tau and gamma; derivatives: see
    ``render_batched``)."""
    dt = jnp.result_type(camera.pos.dtype, geoms.xpos.dtype)
    cam, geo = native_inputs(R, camera, geoms, dt)
    G, H, W = R.ngeom, camera.height, camera.width
    sds = jax.ShapeDtypeStruct
    rgb, depth, seg, body, w, bg = native_call(R, 
        target, (sds((H, W, 3), dt), sds((H, W), dt), sds((H, W), jnp.int32),
                 sds((H, W), jnp.int32), sds((H, W, G), dt), sds((H, W), dt)),
        cam, geo, jnp.asarray(tg, dt))
    return Images(rgb=rgb, depth=depth, segmentation=seg, body=body, weights=w,
                  background=bg)


def pullback_native(R, camera: Camera, geoms: Geoms, tg, ct: Images, target: str):
    """The cotangents of ``camera`` and ``geoms`` from those of an image (``ct``): the C++
    reverse kernel, then the packing of its inputs (``native_inputs``) in JAX."""
    from twinrl.render import native

    dt = jnp.result_type(camera.pos.dtype, geoms.xpos.dtype)
    (cam, geo), pull = jax.vjp(lambda c, g: native_inputs(R, c, g, dt), camera, geoms)
    sds = jax.ShapeDtypeStruct
    gcam, ggeo = native_call(R, 
        native.VJP_TARGETS[target], (sds(cam.shape, dt), sds(geo.shape, dt)), cam, geo,
        jnp.asarray(tg, dt), *(jnp.asarray(x, dt) for x in (ct.rgb, ct.depth, ct.weights,
                                                             ct.background)))
    return pull((gcam, ggeo))
