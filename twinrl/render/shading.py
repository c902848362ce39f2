"""Shading: OpenGL's fixed-function model as MuJoCo configures it (headlight and scene lights:
ambient + Lambertian diffuse + Blinn-Phong specular, spot cone and exponent, attenuation), and
hard shadows (one shadow ray per pixel and light, no gradient).

``lights`` reads a model's lights once (``Renderer.create``); the other functions take the
``Renderer`` ``R`` first.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from twinrl.render import primitives as prim
from twinrl.render.cast import cast_mesh, cast_prim, group_params, select
from twinrl.render.scene import MESH


def lights(model: mujoco.MjModel):
    """The active lights of ``model`` as NumPy arrays: world position and direction (after
    ``mj_camlight``), type, colours, spot cutoff and exponent, attenuation, ``castshadow``."""
    d = mujoco.MjData(model)
    mujoco.mj_kinematics(model, d)
    mujoco.mj_camlight(model, d)
    on = np.flatnonzero(np.asarray(model.light_active, bool))
    ltype = np.asarray(model.light_type)[on] if hasattr(model, "light_type") else np.where(
        np.asarray(model.light_directional)[on], 1, 0)
    return dict(
        pos=np.asarray(d.light_xpos[on], np.float64),
        dir=np.asarray(d.light_xdir[on], np.float64),
        type=np.asarray(ltype, np.int32),
        ambient=np.asarray(model.light_ambient[on], np.float64),
        diffuse=np.asarray(model.light_diffuse[on], np.float64),
        specular=np.asarray(model.light_specular[on], np.float64),
        cutoff=np.asarray(model.light_cutoff[on], np.float64),
        exponent=np.asarray(model.light_exponent[on], np.float64),
        attenuation=np.asarray(model.light_attenuation[on], np.float64),
        castshadow=np.asarray(model.light_castshadow[on], bool),
    )


def geom_albedo(R, rgba):
    """Each drawn geom's colour (G, 4): its material's where MuJoCo colours it by the material."""
    return jnp.where(jnp.asarray(R.use_mat_rgba)[:, None],
                     jnp.asarray(R.mat_rgba, rgba.dtype), rgba)


def light_dir(R, i, p):
    """Unit direction to light ``i``, its distance and its attenuation/spot factor at ``p``."""
    L = R.lights
    if L["type"][i] == 1:  # directional
        l = jnp.broadcast_to(-jnp.asarray(L["dir"][i], p.dtype), p.shape)
        return l, jnp.full(p.shape[:-1], 1e9, p.dtype), jnp.ones(p.shape[:-1], p.dtype)
    dl = jnp.asarray(L["pos"][i], p.dtype) - p
    dist_l = jnp.sqrt(prim.dot(dl, dl) + 1e-20)
    l = dl / dist_l[..., None]
    a = L["attenuation"][i]
    factor = 1.0 / (a[0] + a[1] * dist_l + a[2] * dist_l ** 2)
    if L["type"][i] == 0:  # spot: cone and exponent
        cosang = -prim.dot(l, jnp.asarray(L["dir"][i], p.dtype))
        inside = cosang >= np.cos(np.deg2rad(L["cutoff"][i]))
        factor = factor * jnp.where(
            inside, jnp.exp(L["exponent"][i] * jnp.log(jnp.maximum(cosang, 1e-30))), 0.0)
    return l, dist_l, factor


def shade(R, p, n, view_o, forward, albedo, mat, lit):
    """OpenGL fixed-function colour of surface points ``p`` (..., S, 3), normals ``n``, of
    geoms with ``albedo`` (..., S, 4) and ``mat`` (..., S, 3) (specular, shininess,
    emission); ``lit`` {light: (...,)} the shadow factor of each shadow-casting light."""
    v = view_o - p
    v = v / jnp.sqrt(prim.dot(v, v) + 1e-20)[..., None]
    # No two-sided flip: closed geoms are only ever seen from outside, and at a soft
    # silhouette (n . v ~ 0) a flip would make the colour jump.
    rgb = albedo[..., :3]
    spec_m = mat[..., 0:1]
    shin = 128.0 * mat[..., 1]
    col = mat[..., 2:3] * rgb

    def light(col, l, amb, dif, spe, factor):
        ndl = prim.dot(n, l)
        h = l + v
        h = h / jnp.sqrt(prim.dot(h, h) + 1e-20)[..., None]
        ndh = jnp.maximum(prim.dot(n, h), 0.0)
        # x ** shin as exp(shin log x): XLA on CPU vectorises exp and log, not pow
        spec = jnp.where(ndl > 0, jnp.exp(shin * jnp.log(ndh + 1e-30)), 0.0)
        return (col + amb * rgb + factor[..., None] * (
            dif * jnp.maximum(ndl, 0.0)[..., None] * rgb + spe * spec_m * spec[..., None]))

    hl = R.headlight
    if hl["active"]:
        l = jnp.broadcast_to(-forward, p.shape)
        col = light(col, l, jnp.asarray(hl["ambient"], p.dtype),
                    jnp.asarray(hl["diffuse"], p.dtype), jnp.asarray(hl["specular"], p.dtype),
                    jnp.ones(p.shape[:-1], p.dtype))
    L = R.lights
    for i in range(len(L["type"])):
        l, _, factor = light_dir(R, i, p)
        if i in lit:
            factor = factor * lit[i][..., None]
        col = light(col, l, jnp.asarray(L["ambient"][i], p.dtype),
                    jnp.asarray(L["diffuse"][i], p.dtype),
                    jnp.asarray(L["specular"][i], p.dtype), factor)
    return jnp.clip(col, 0.0, 1.0)


def unoccluded(R, p, l, dist_l, skip, geoms):
    """1 where the ray from ``p`` (..., 3) towards the light (``l``, ``dist_l`` away) meets
    no geom other than ``skip`` (..., renderer index), else 0; no gradient (hard shadows)."""
    sg = jax.lax.stop_gradient
    p, l, dist_l = sg(p), sg(l), sg(dist_l)
    geoms = jax.tree_util.tree_map(sg, geoms)
    xpos, xmat, size, _ = select(R, geoms)
    o = p + 1e-5 * l
    blocked = jnp.zeros(p.shape[:-1], bool)
    none = jnp.zeros((R.ngeom, 0), p.dtype)
    for t, idx in R.groups():
        if t == 0:
            continue  # a plane is seen from its front only: it casts no shadow upwards
        if t == MESH:
            s = cast_mesh(R, o, l, geoms, xpos, xmat, idx, False, R.iters)[0]
            gid = jnp.asarray(idx, jnp.int32)
        else:
            gx, gm, gs, _, gid, _, _ = group_params(R, t, idx, o, l, xpos, xmat, size,
                                                          none, None, 0.0)
            s = cast_prim(R, t, o, l, gx, gm, gs, False, R.iters,
                                differentiable=False)[0]
        blocked = blocked | jnp.any((gid != skip[..., None]) & (s < dist_l[..., None]), -1)
    return 1.0 - blocked.astype(p.dtype)
