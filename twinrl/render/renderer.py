"""A differentiable ray-casting renderer of an MJX scene: RGB, depth, segmentation, soft masks.

SAM-RL (Lv et al., 2023), Sec. 3.2 ("differentiable rendering") fits the simulator's camera and
objects to real RGB-D frames by gradient descent through a renderer; this is that renderer for
MuJoCo scenes. Each pixel's ray is intersected analytically with every visible geom (plane,
sphere, capsule, ellipsoid, cylinder, box; meshes through their triangles), so the *hard* image is
exact and matches ``mujoco.Renderer``'s OpenGL depth and segmentation (up to OpenGL's tessellation
of curved geoms). The hard image has no gradient when a silhouette moves (a pixel switches
between geoms discontinuously), so the *soft* image (``tau > 0``) follows SoftRas (Liu et al.,
2019, Sec. 3.2-3.3): each geom covers a pixel with probability ``sigmoid(-d / tau)``, ``d`` the
signed distance (in pixels) of the pixel's ray to the geom's boundary, and the coverages are
composited front to back with a smooth depth order (temperature ``gamma``, metres) in place of
SoftRas's softmax-of-inverse-depth aggregation; the background takes what no geom covers. As
``tau, gamma -> 0`` the soft image tends to the hard one.

Shading is OpenGL's fixed-function model as MuJoCo configures it (the headlight and the scene's
lights: ambient + Lambertian diffuse + Blinn-Phong specular, spot cone and exponent, attenuation),
with hard shadows of the lights that cast them (treated as constants for gradients): one shadow
ray per pixel and light, from the surface that shows most at that pixel (the hard image's hit),
whose verdict shades every geom's point at that pixel (exact in the hard image; in the soft image
it shades the other geoms' edge pixels too).

Cost. Every pixel is tested against every plane and mesh, and against at most ``per_pixel`` geoms
of each other primitive type that has more than ``cull_above`` (8) of them: per pixel, the nearest
whose bounding capsule its ray passes through or near (a rasteriser's culling, with the static
shapes XLA needs); and only the ``layers`` surfaces that show most at a pixel are composited (a
cost quadratic in their number) and shaded. A scene with at most ``max(per_pixel, cull_above)``
geoms of each type and ``layers`` geoms in all is drawn exactly as without either; beyond, the
hard image stays exact and the soft one loses only the coverage of surfaces crowded out of a
pixel (``bench/render.py``'s sweep measures how much). Neither rule lets a geom that adds nothing
to a pixel decide anything there: a culled pick beyond the soft band (it fills one of the
``per_pixel`` places where fewer geoms are near) covers nothing, and a surface whose coverage the
dtype cannot resolve (``negligible_coverage``) ranks below every other when the layers are chosen.
A ray's first hit is found in closed form
and differentiated implicitly (``primitives.hit_implicit``); a ``jax.vmap``-ed render of more
(pixel, surface) pairs than ``BATCH_ELEMENTS`` is drawn a chunk of cameras at a time, so that its
arrays stay in the CPU's caches (``_render_batched``; derivatives go through the whole batch).
On the CPU a C++ kernel of the same arithmetic draws the images (``twinrl.render.native``:
packets of pixels in SIMD lanes, built on first use; JAX where there is no compiler, and for
meshes), and its reverse pass gives their gradients (``jax.grad``, ``jax.vjp``); forward mode
(``jax.jvp``, ``jax.jacfwd``) and second derivatives go through this JAX version.

Everything is a pure function of ``Camera`` and ``Geoms`` pytrees: jit, vmap (batches of cameras
or scenes) and grad reach the camera pose and intrinsics, geom poses (``geom_xpos``/``geom_xmat``
of an ``mjx.Data``), ``geom_size``, ``geom_rgba`` and mesh vertices.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.custom_derivatives import SymbolicZero

from twinrl._jaxconfig import exact_matmuls
from twinrl.render import linear
from twinrl.render import primitives as prim
from twinrl.render.camera import Camera

__all__ = ["Geoms", "Images", "Renderer", "UnsupportedGeomError"]

_MESH = 7


def negligible_coverage(dtype) -> float:
    """The coverage below which a surface counts as covering nothing when the layers are chosen:
    sigmoid(-18) ~ 1.5e-8 in float32 (a quarter of its resolution at 1), sigmoid(-30) ~ 9.4e-14
    in float64. Such a surface ranks below every other (it cannot take a hidden surface's place),
    and the C++ kernel neither searches nor differentiates one whose rays all pass that far from
    its silhouette (``twinrl.render.native``)."""
    return 9.357622968840175e-14 if jnp.dtype(dtype) == jnp.float64 else 1.5229979744712629e-08


class UnsupportedGeomError(ValueError):
    """A geom type the renderer cannot draw (height fields, SDF plugins)."""


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Geoms:
    """What the renderer draws, for *all* geoms of a model (the renderer picks the visible ones):
    world poses ``xpos`` (G, 3), ``xmat`` (G, 3, 3), ``size`` (G, 3), ``rgba`` (G, 4) and the
    model's ``mesh_vert`` (V, 3) (mesh-local vertices; (0, 3) without meshes)."""

    xpos: jax.Array
    xmat: jax.Array
    size: jax.Array
    rgba: jax.Array
    mesh_vert: jax.Array

    @classmethod
    def from_mjx(cls, model, data, *, kinematics: bool = True) -> "Geoms":
        """Geoms of an ``mjx.Model``/``mjx.Data``; ``kinematics=True`` first recomputes the poses
        from ``qpos`` (``mjx.kinematics``), so gradients reach ``qpos`` and the model."""
        if kinematics:
            data = _kinematics()(model, data)
        return cls(data.geom_xpos, data.geom_xmat.reshape(-1, 3, 3), model.geom_size,
                   model.geom_rgba, jnp.asarray(model.mesh_vert).reshape(-1, 3))

    @classmethod
    def from_mujoco(cls, model: mujoco.MjModel, data: mujoco.MjData, dtype=None) -> "Geoms":
        """Geoms of a MuJoCo C model/data (after ``mj_forward`` or ``mj_kinematics``)."""
        dt = dtype or jnp.result_type(float)
        return cls(jnp.asarray(data.geom_xpos, dt),
                   jnp.asarray(data.geom_xmat, dt).reshape(-1, 3, 3),
                   jnp.asarray(model.geom_size, dt), jnp.asarray(model.geom_rgba, dt),
                   jnp.asarray(model.mesh_vert, dt).reshape(-1, 3))

    def replace(self, **kw) -> "Geoms":
        return dataclasses.replace(self, **kw)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Images:
    """A rendered frame. ``rgb`` (H, W, 3) in [0, 1]; ``depth`` (H, W) metres along the viewing
    axis (far plane where nothing is seen); ``segmentation`` (H, W) int32 geom ids and ``body``
    (H, W) body ids of the *hard* image (-1: background); ``weights`` (H, W, G) each drawn geom's
    share of the pixel (``Renderer.geom_ids`` order; soft when ``tau > 0``, else one-hot);
    ``background`` (H, W) the background's share."""

    rgb: jax.Array
    depth: jax.Array
    segmentation: jax.Array
    body: jax.Array
    weights: jax.Array
    background: jax.Array


def _gl_far_depth(near: float, far: float) -> float:
    """The depth ``mujoco.Renderer`` reports where nothing is drawn: its reverse-Z projection
    evaluated in float32 at depth-buffer value 0 (a few mm from ``far`` for large scenes), so
    background pixels compare equal."""
    zf, zn = np.float32(far), np.float32(near)
    c = -(zf + zn) / (zf - zn)
    d = -(np.float32(2) * zf * zn) / (zf - zn)
    c = np.float32(-0.5) * c - np.float32(0.5)
    d = np.float32(-0.5) * d
    return float(np.float32(np.float64(d) / (0.0 + np.float64(c))))


def _lights(model: mujoco.MjModel):
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


@functools.cache
def _kinematics():
    """``mjx.kinematics`` jitted: inside an outer trace, one equation whose trace (and its
    derivatives and batched forms) every render of a model's state reuses -- tracing MJX's
    kinematics of the arm takes seconds, and a camera ascent renders the same state twice."""
    from mujoco import mjx

    return jax.jit(mjx.kinematics)


def _hashable(x):
    """A value's hashable, comparable stand-in: arrays by dtype, shape and bytes, dicts by their
    sorted items."""
    if isinstance(x, np.ndarray):
        return ("ndarray", x.dtype.str, x.shape, x.tobytes())
    if isinstance(x, dict):
        return ("dict",) + tuple((k, _hashable(v)) for k, v in sorted(x.items()))
    if isinstance(x, (list, tuple)):
        return (type(x).__name__,) + tuple(_hashable(v) for v in x)
    return x


def _to_local(v, xmat):
    """``v @ xmat`` per geom: ``v`` (..., g, 3); ``xmat`` (g, 3, 3) shared by every ray (a
    batched matrix product) or (..., g, 3, 3) per ray (written out elementwise, so it fuses)."""
    if xmat.ndim == 3:
        return jnp.einsum("...gi,gij->...gj", v, xmat)
    return (v[..., 0:1] * xmat[..., 0, :] + v[..., 1:2] * xmat[..., 1, :]
            + v[..., 2:3] * xmat[..., 2, :])


def _to_world(v, xmat):
    """``xmat @ v`` per geom (the inverse of ``_to_local``)."""
    if xmat.ndim == 3:
        return jnp.einsum("...gj,gij->...gi", v, xmat)
    return (v[..., 0:1] * xmat[..., :, 0] + v[..., 1:2] * xmat[..., :, 1]
            + v[..., 2:3] * xmat[..., :, 2])


@dataclasses.dataclass(frozen=True, eq=False)
class Renderer:
    """Renders one ``mujoco.MjModel``'s geoms; holds only static structure (geom types, mesh
    faces, lights, near/far planes), so its methods jit with it closed over. Two renderers of
    the same structure are equal (and hash alike), so they share compiled renders.

    Args:
      model: the ``mujoco.MjModel`` (the MJX model's source).
      geom_ids: geoms to draw (default: those MuJoCo draws by default: groups 0-2, alpha > 0).
      shadows: shadow rays for lights with ``castshadow`` (as ``mujoco.Renderer`` draws them).
      iters: golden-section iterations of the soft closest-approach search (cylinders, meshes;
        boxes are solved exactly); the soft silhouette is placed to about ``0.62**iters`` of
        the geom's size.
      per_pixel: how many geoms of one primitive type (sphere, capsule, ...) each pixel's ray is
        tested against, at most, in a type that is culled (planes and meshes: never culled).
        Culling (``_choose``) keeps, per pixel, the geoms whose bounding capsule the ray passes
        through, nearest first, then those it passes within the soft silhouette's band of; the
        others contribute nothing there. Exact while no pixel has more candidates of one type.
      cull_above: a type is culled only when it has more than ``max(per_pixel, cull_above)``
        geoms; smaller types are drawn whole, exactly. Culling switches the whole image to a
        per-pixel layout (every group's shading inputs per pixel, one-hot gathers back to geoms)
        that costs more than it saves unless it removes many candidates: 64x64 soft images with
        the gradient, 2 CPU cores, drawing all of peg insertion's 8 capsules and 5 boxes is 2.4x
        faster than culling them to 4, and a 21-geom chain's ~5 of each type 1.7x, while
        spatula flipping's 16 capsules are 1.2x faster culled (``bench/render.py``). 0: cull
        every type with more than ``per_pixel`` geoms.
      layers: how many surfaces each pixel composites and shades, at most: the most covering of
        those not hidden behind a solid one. The hard image is exact whatever its value; the soft
        one drops at most the coverage of a pixel's ``layers + 1``-th surface.
    """

    geom_ids: tuple[int, ...]
    types: tuple[int, ...]
    bodies: np.ndarray
    specular: np.ndarray
    shininess: np.ndarray
    emission: np.ndarray
    mat_rgba: np.ndarray
    use_mat_rgba: np.ndarray
    lights: dict
    headlight: dict
    near: float
    far: float
    """Far clipping plane (m); background depth is ``far_depth``."""
    far_depth: float
    tri_geom: np.ndarray
    tri_vert: np.ndarray
    shadows: bool = True
    iters: int = 16
    per_pixel: int = 4
    layers: int = 8
    cull_above: int = 8

    @classmethod
    def create(cls, model: mujoco.MjModel, *, geom_ids: Sequence[int] | None = None,
               shadows: bool = True, iters: int = 16, per_pixel: int = 4,
               layers: int = 8, cull_above: int = 8) -> "Renderer":
        if not isinstance(model, mujoco.MjModel):
            raise TypeError(f"model must be a mujoco.MjModel, got {type(model).__name__}")
        if geom_ids is None:
            geom_ids = [g for g in range(model.ngeom)
                        if model.geom_group[g] < 3 and model.geom_rgba[g, 3] > 0]
        geom_ids = tuple(int(g) for g in geom_ids)
        if int(per_pixel) < 1 or int(layers) < 1:
            raise ValueError(f"per_pixel and layers must be >= 1, got {per_pixel}, {layers}")
        if int(cull_above) < 0:
            raise ValueError(f"cull_above must be >= 0, got {cull_above}")
        if not geom_ids:
            raise ValueError("no geom to draw")
        for g in geom_ids:
            if not 0 <= g < model.ngeom:
                raise ValueError(f"geom id {g} out of range [0, {model.ngeom})")
            t = int(model.geom_type[g])
            if t not in prim.PRIMITIVES and t != _MESH:
                raise UnsupportedGeomError(
                    f"geom {g} ({model.geom(g).name or 'unnamed'}) has type "
                    f"{prim.GEOM_NAMES.get(t, t)!r}; the renderer draws plane, sphere, capsule, "
                    "ellipsoid, cylinder, box and mesh")
        gi = np.asarray(geom_ids)
        matid = np.asarray(model.geom_matid)[gi]
        has = matid >= 0
        spec = np.where(has, model.mat_specular[np.maximum(matid, 0)] if model.nmat else 0.5, 0.5)
        shin = np.where(has, model.mat_shininess[np.maximum(matid, 0)] if model.nmat else 0.5, 0.5)
        emis = np.where(has, model.mat_emission[np.maximum(matid, 0)] if model.nmat else 0.0, 0.0)
        mat_rgba = (model.mat_rgba[np.maximum(matid, 0)] if model.nmat
                    else np.ones((len(gi), 4)))
        # MuJoCo colours a geom by its material unless the geom's own rgba was set explicitly
        # (compiled, that shows as an rgba different from the default grey).
        default = np.array([0.5, 0.5, 0.5, 1.0])
        use_mat = has & np.all(np.isclose(model.geom_rgba[gi], default), -1)
        tri_geom, tri_vert = [], []
        for k, g in enumerate(geom_ids):
            if model.geom_type[g] == _MESH:
                mid = int(model.geom_dataid[g])
                va, fa, fn = (int(model.mesh_vertadr[mid]), int(model.mesh_faceadr[mid]),
                              int(model.mesh_facenum[mid]))
                faces = np.asarray(model.mesh_face[fa:fa + fn]) + va
                tri_vert.append(faces)
                tri_geom.append(np.full(fn, k))
        ext = float(model.stat.extent)
        vis = model.vis
        return cls(
            geom_ids=geom_ids, types=tuple(int(model.geom_type[g]) for g in geom_ids),
            bodies=np.asarray(model.geom_bodyid)[gi].astype(np.int32),
            specular=np.asarray(spec, np.float64), shininess=np.asarray(shin, np.float64),
            emission=np.asarray(emis, np.float64), mat_rgba=np.asarray(mat_rgba, np.float64),
            use_mat_rgba=use_mat, lights=_lights(model),
            headlight=dict(active=bool(vis.headlight.active),
                           ambient=np.asarray(vis.headlight.ambient, np.float64),
                           diffuse=np.asarray(vis.headlight.diffuse, np.float64),
                           specular=np.asarray(vis.headlight.specular, np.float64)),
            near=float(vis.map.znear) * ext, far=float(vis.map.zfar) * ext,
            far_depth=_gl_far_depth(float(vis.map.znear) * ext, float(vis.map.zfar) * ext),
            tri_geom=np.concatenate(tri_geom) if tri_geom else np.zeros(0, np.int32),
            tri_vert=np.concatenate(tri_vert) if tri_vert else np.zeros((0, 3), np.int32),
            shadows=bool(shadows), iters=int(iters), per_pixel=int(per_pixel),
            layers=int(layers), cull_above=int(cull_above))

    # Equal (and hashed) by content, not identity: ``render`` jits with the renderer static, so
    # two renderers of the same scene (two tasks made from one MJCF, a task and its real twin)
    # share one trace of the image, its gradient and its batched forms per process (and, called
    # outside jit, one compile per image size) instead of one each.
    @functools.cached_property
    def _content(self) -> tuple:
        return tuple(_hashable(getattr(self, f.name)) for f in dataclasses.fields(self))

    def __eq__(self, other) -> bool:
        if self is other:
            return True
        return type(other) is type(self) and self._content == other._content

    def __hash__(self) -> int:
        return hash(self._content)

    @property
    def ngeom(self) -> int:
        return len(self.geom_ids)

    def index(self, geom_id: int) -> int:
        """Position of model geom ``geom_id`` in ``Images.weights``' last axis."""
        if geom_id not in self.geom_ids:
            raise ValueError(f"geom {geom_id} is not drawn by this renderer ({self.geom_ids})")
        return self.geom_ids.index(geom_id)

    # ------------------------------------------------------------------ ray casting
    def _select(self, geoms: Geoms):
        gi = np.asarray(self.geom_ids)
        if geoms.xpos.ndim != 2 or geoms.xpos.shape[-1] != 3 or geoms.xmat.shape[-2:] != (3, 3):
            raise ValueError(f"Geoms.xpos must be (G, 3) and xmat (G, 3, 3); got "
                             f"{geoms.xpos.shape}, {geoms.xmat.shape} (vmap batches of scenes)")
        if geoms.xpos.shape[0] <= gi.max():
            raise ValueError(f"Geoms has {geoms.xpos.shape[0]} geoms; this renderer draws geom "
                             f"{gi.max()}: render with Geoms of the renderer's own model")
        return (geoms.xpos[gi], geoms.xmat[gi], geoms.size[gi], geoms.rgba[gi])

    def _triangles(self, geoms: Geoms, xpos, xmat):
        k = jnp.asarray(self.tri_geom)
        v = geoms.mesh_vert[jnp.asarray(self.tri_vert)]  # (T, 3, 3) local
        return jnp.einsum("tij,tcj->tci", xmat[k], v) + xpos[k][:, None, :]

    def cast(self, o, r, geoms: Geoms, *, soft: bool = False, iters: int | None = None,
             normal_tau=None):
        """Intersect rays ``o + s r`` (o (..., 3) or (3,), r (..., 3)) with every drawn geom.

        Returns ``s_hit`` (..., G) (inf: no hit), and with ``soft`` also ``s_near`` (..., G) (the
        hit, else the closest approach), ``dist`` (..., G) signed distance (m) of the ray to the
        geom's boundary and unit world ``normal`` (..., G, 3) at ``o + s_near r``, blended
        across edges over ``normal_tau * s_near`` metres (``normal_tau`` (...,): metres per unit
        depth; None: hard).
        """
        xpos, xmat, size, _ = self._select(geoms)
        iters = self.iters if iters is None else iters
        batch = r.shape[:-1]
        G = self.ngeom
        s_hit = [None] * G
        s_near, dist, normal = [None] * G, [None] * G, [None] * G
        types = np.asarray(self.types)
        for t in sorted(set(self.types)):
            idx = np.flatnonzero(types == t)
            if t == _MESH:
                out = self._cast_mesh(o, r, geoms, xpos, xmat, idx, soft, iters, normal_tau)
            else:
                out = self._cast_prim(t, o, r, xpos[idx], xmat[idx], size[idx], soft, iters,
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

    def _cast_prim(self, t, o, r, xpos, xmat, size, soft, iters, normal_tau=None,
                   hard_normals=False, differentiable=True):
        """One primitive type's geoms: ``xpos`` (g, 3), ``xmat`` (g, 3, 3), ``size`` (g, 3) for
        every ray, or (..., g, 3[, 3]) per ray (the geoms culling chose for each pixel).
        ``differentiable=False``: the hits of rays whose gradient nobody takes (shadow rays)."""
        _, hit, closest, normal = prim.PRIMITIVES[t]
        # local frame: p_loc = xmat^T (p - xpos)
        o_l = _to_local(o[..., None, :] - xpos, xmat)
        r_l = (jnp.einsum("...i,gij->...gj", r, xmat) if xmat.ndim == 3
               else _to_local(r[..., None, :], xmat))
        s_hit = prim.hit_implicit(t, o_l, r_l, size) if differentiable else hit(o_l, r_l, size)
        if not soft:
            if not hard_normals:
                return (s_hit,)
            p = o_l + jnp.where(jnp.isfinite(s_hit), s_hit, self.far)[..., None] * r_l
            n = _to_world(normal(p, size), xmat)
            return s_hit, n / jnp.sqrt(prim.dot(n, n) + 1e-20)[..., None]
        s_c, d = closest(o_l, r_l, size, iters)
        s_n = jnp.where(jnp.isfinite(s_hit), s_hit, s_c)
        s_n = jnp.where(jnp.isfinite(s_n), s_n, self.far)
        p = o_l + s_n[..., None] * r_l
        tn = None if normal_tau is None else normal_tau[..., None] * s_n
        n = _to_world(normal(p, size, tn), xmat)
        n = n / jnp.sqrt(prim.dot(n, n) + 1e-20)[..., None]
        return s_hit, s_n, d, n

    def _cast_mesh(self, o, r, geoms, xpos, xmat, idx, soft, iters, normal_tau=None):
        tri = self._triangles(geoms, xpos, xmat)  # (T, 3, 3) world
        k = np.asarray(self.tri_geom)
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

    def sdf(self, points: jax.Array, geoms: Geoms) -> jax.Array:
        """Signed distance (m) of world ``points`` (..., 3) to each drawn geom's surface
        (..., G): exact for sphere, capsule, box, cylinder, plane (|z| inside its rectangle);
        approximate for ellipsoids; a convex mesh's largest face-plane distance."""
        xpos, xmat, size, _ = self._select(geoms)
        types = np.asarray(self.types)
        out = [None] * self.ngeom
        for t in sorted(set(self.types)):
            idx = np.flatnonzero(types == t)
            if t == _MESH:
                fn, off, sel = self._face_planes(geoms, xpos, xmat, idx)
                vals = jnp.where(sel, (points @ fn.T - off)[..., None, :], -jnp.inf)
                d = jnp.max(vals, -1)
            else:
                p = jnp.einsum("...gi,gij->...gj", points[..., None, :] - xpos[idx], xmat[idx])
                d = prim.sdf(t, p, size[idx])
            for j, g in enumerate(idx):
                out[g] = d[..., j]
        return jnp.stack(out, -1)

    # ------------------------------------------------------------------ culling
    def _groups(self):
        """The drawn geoms by primitive type: ``[(type, renderer indices)]`` (static)."""
        types = np.asarray(self.types)
        return [(t, np.flatnonzero(types == t)) for t in sorted(set(self.types))]

    def _culled(self, t, idx) -> bool:
        return t not in (0, _MESH) and len(idx) > max(self.per_pixel, self.cull_above)

    def _choose(self, t, idx, o, r, xpos, xmat, size, reach, front):
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
        depth = jnp.maximum(s_c, self.near)
        lim = rad if reach is None else rad + reach[..., None] * depth
        core = dist <= rad * 1.001 + 1e-6
        band = (dist <= lim * 1.001 + 1e-6) & (s_c + half + rad >= front)
        near = core & (s_c + half + rad >= front)
        score = jnp.where(near, 1e6 - s_c, jnp.where(band, -(dist - rad) / depth, -1e9 - dist))
        k = jax.lax.top_k(score, self.per_pixel)[1]
        return (k, (k[..., None] == jnp.arange(len(idx))).astype(r.dtype),
                jnp.take_along_axis(near | band, k, -1))

    def _group_params(self, t, idx, o, r, xpos, xmat, size, extra, reach, front, const=None):
        """Per group of one type: the geoms' (or, culled, each ray's chosen geoms') ``xpos``,
        ``xmat``, ``size``, ``extra`` (G, E) per-geom columns, renderer indices ``gid`` ((n,)
        static, else (..., K)), the rows of the NumPy table ``const`` (G, C), and (culled)
        whether each choice is near the ray (``_choose``; else None)."""
        dt = xpos.dtype
        if not self._culled(t, idx):
            return (xpos[idx], xmat[idx], size[idx], extra[idx], jnp.asarray(idx, jnp.int32),
                    None if const is None else jnp.asarray(const[idx], dt), None)
        k, oh, near = self._choose(t, idx, o, r, xpos, xmat, size, reach, front)
        n = len(idx)
        table = jnp.concatenate([xpos[idx], xmat[idx].reshape(n, 9), size[idx], extra[idx]], -1)
        # a one-hot matrix product, not a gather: its reverse pass is another product (a gather's
        # is a scatter, which XLA on CPU runs serially)
        tab = jnp.einsum("...kn,nd->...kd", oh, table)
        return (tab[..., 0:3], tab[..., 3:12].reshape(*tab.shape[:-1], 3, 3), tab[..., 12:15],
                tab[..., 15:], jnp.asarray(idx, jnp.int32)[k],
                None if const is None else oh @ jnp.asarray(const[idx], dt), near)

    # ------------------------------------------------------------------ shading
    def _albedo(self, rgba):
        return jnp.where(jnp.asarray(self.use_mat_rgba)[:, None],
                         jnp.asarray(self.mat_rgba, rgba.dtype), rgba)

    def _light_dir(self, i, p):
        """Unit direction to light ``i``, its distance and its attenuation/spot factor at ``p``."""
        L = self.lights
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

    def _shade(self, p, n, view_o, forward, albedo, mat, lit):
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

        hl = self.headlight
        if hl["active"]:
            l = jnp.broadcast_to(-forward, p.shape)
            col = light(col, l, jnp.asarray(hl["ambient"], p.dtype),
                        jnp.asarray(hl["diffuse"], p.dtype), jnp.asarray(hl["specular"], p.dtype),
                        jnp.ones(p.shape[:-1], p.dtype))
        L = self.lights
        for i in range(len(L["type"])):
            l, _, factor = self._light_dir(i, p)
            if i in lit:
                factor = factor * lit[i][..., None]
            col = light(col, l, jnp.asarray(L["ambient"][i], p.dtype),
                        jnp.asarray(L["diffuse"][i], p.dtype),
                        jnp.asarray(L["specular"][i], p.dtype), factor)
        return jnp.clip(col, 0.0, 1.0)

    def _unoccluded(self, p, l, dist_l, skip, geoms):
        """1 where the ray from ``p`` (..., 3) towards the light (``l``, ``dist_l`` away) meets
        no geom other than ``skip`` (..., renderer index), else 0; no gradient (hard shadows)."""
        sg = jax.lax.stop_gradient
        p, l, dist_l = sg(p), sg(l), sg(dist_l)
        geoms = jax.tree_util.tree_map(sg, geoms)
        xpos, xmat, size, _ = self._select(geoms)
        o = p + 1e-5 * l
        blocked = jnp.zeros(p.shape[:-1], bool)
        none = jnp.zeros((self.ngeom, 0), p.dtype)
        for t, idx in self._groups():
            if t == 0:
                continue  # a plane is seen from its front only: it casts no shadow upwards
            if t == _MESH:
                s = self._cast_mesh(o, l, geoms, xpos, xmat, idx, False, self.iters)[0]
                gid = jnp.asarray(idx, jnp.int32)
            else:
                gx, gm, gs, _, gid, _, _ = self._group_params(t, idx, o, l, xpos, xmat, size,
                                                              none, None, 0.0)
                s = self._cast_prim(t, o, l, gx, gm, gs, False, self.iters,
                                    differentiable=False)[0]
            blocked = blocked | jnp.any((gid != skip[..., None]) & (s < dist_l[..., None]), -1)
        return 1.0 - blocked.astype(p.dtype)

    # ------------------------------------------------------------------ images
    @exact_matmuls
    def render(self, camera: Camera, geoms: Geoms, *, tau: float = 0.0,
               gamma: float = 0.01) -> Images:
        """Render ``geoms`` seen from ``camera``. Called outside ``jit`` with Python-number
        ``tau`` and ``gamma``, it runs one function compiled on its first call per renderer,
        image size, ``tau`` and ``gamma`` (not ~3,000 operations dispatched one by one).

        Args:
          tau: soft-silhouette temperature in pixels (0: the hard image; SoftRas's sigma).
          gamma: depth-order temperature in metres for the soft composite (SoftRas's gamma).
        """
        if not isinstance(camera, Camera):
            raise TypeError(f"camera must be a twinrl.render.Camera, got {type(camera).__name__}")
        if not isinstance(geoms, Geoms):
            raise TypeError(f"geoms must be a twinrl.render.Geoms, got {type(geoms).__name__}")
        if camera.pos.shape != (3,):
            raise ValueError(f"camera.pos must be (3,), got {camera.pos.shape}: "
                             "jax.vmap over a batch of cameras")
        if isinstance(tau, (int, float)) and isinstance(gamma, (int, float)):
            # one compiled function, not ~3,000 operations dispatched one by one (each compiled
            # on its first use) when called outside jit; inside jit, an inlined call
            # which implementation draws an image nobody differentiates is a static argument:
            # traces with and without the C++ kernel are kept apart
            return _render_jit(self, camera, geoms, float(tau), float(gamma),
                               self._native_target(camera, geoms))
        return _render_batched(self, camera, geoms, tau, gamma,
                               self._native_target(camera, geoms))

    def surfaces(self) -> int:
        """How many surfaces each pixel's ray is tested against (per-pixel culling included;
        a mesh counts its triangles)."""
        n = 0
        for t, idx in self._groups():
            n += (len(self.tri_geom) if t == _MESH
                  else self.per_pixel if self._culled(t, idx) else len(idx))
        return n

    def batch_chunk(self, height: int, width: int, batch: int) -> int:
        """How many cameras of a batch of ``batch`` a ``jax.vmap``-ed render draws at once: the
        largest divisor of ``batch`` whose (pixel, surface) pairs stay within
        ``BATCH_ELEMENTS`` (a divisor, so that ``lax.map`` compiles one chunk and no
        remainder)."""
        most = max(1, BATCH_ELEMENTS // max(1, height * width * self.surfaces()))
        return max(k for k in range(1, min(most, batch) + 1) if batch % k == 0)

    def _render(self, camera: Camera, geoms: Geoms, tau, gamma) -> Images:
        soft = not (isinstance(tau, (int, float)) and tau == 0)
        H, W, G = camera.height, camera.width, self.ngeom
        o, r = camera.rays()
        r = r.reshape(-1, 3)
        P = r.shape[0]
        xpos, xmat, size, rgba = self._select(geoms)
        forward = -camera.xmat[:, 2]
        pix = camera.pixel_size()
        albedo = self._albedo(rgba)
        # specular, shininess, emission: constants, kept apart from the albedo so that the
        # reverse pass does not differentiate the shading with respect to them
        mat = np.stack([self.specular, self.shininess, self.emission], -1)
        # how far from a geom's bounding sphere a ray may pass and still be tested against it:
        # the soft silhouette's band (coverage sigmoid(-d / tau) < 1e-6 beyond 14 tau pixels)
        band = (15.0 * tau + 2.0) if soft else 2.0
        reach = jnp.broadcast_to(band * pix, (P,))
        ntau = jnp.broadcast_to(tau * pix, (P,)) if soft else None
        parts = []  # per group: s_hit, s_near, dist, normal, shading inputs, renderer index
        for t, idx in self._groups():
            if t == _MESH:
                out = self._cast_mesh(o, r, geoms, xpos, xmat, idx, soft, self.iters, ntau)
                ex, gid = albedo[idx], jnp.asarray(idx, jnp.int32)
                mt = jnp.asarray(mat[idx], albedo.dtype)
                if not soft:
                    out = (out[0], self._mesh_normals(o, r, out[0], geoms, xpos, xmat, idx))
            else:
                gx, gm, gs, ex, gid, mt, near = self._group_params(
                    t, idx, o, r, xpos, xmat, size, albedo, reach, self.near, mat)
                out = self._cast_prim(t, o, r, gx, gm, gs, soft, self.iters, ntau,
                                      hard_normals=not soft)
                if soft and near is not None:  # a pick beyond the band covers nothing
                    out = (out[0], out[1], jnp.where(near, out[2], 1e6), *out[3:])
            parts.append((*out, ex, mt, gid))
        if any(self._culled(t, idx) for t, idx in self._groups()):
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
        s_hit = jnp.where((s_hit >= self.near) & (s_hit <= self.far), s_hit, jnp.inf)
        hit = jnp.isfinite(s_hit)
        first = jnp.argmin(s_hit, -1)
        any_hit = jnp.any(hit, -1)
        g_first = (gid[first] if gid.ndim == 1
                   else jnp.take_along_axis(gid, first[:, None], -1)[:, 0])
        seg = jnp.where(any_hit, jnp.asarray(self.geom_ids, jnp.int32)[g_first], -1).reshape(H, W)
        body = jnp.where(any_hit, jnp.asarray(self.bodies)[g_first], -1).reshape(H, W)
        if not soft:
            s_n = jnp.where(hit, s_hit, self.far)
            cover = hit.astype(r.dtype)
        else:
            d_px = dist / (jnp.maximum(s_n, self.near) * pix)
            cover = jax.nn.sigmoid(-d_px / tau) * ((s_n >= self.near) & (s_n <= self.far))
        z = s_n
        p = o + s_n[..., None] * r[:, None, :]
        oh = None
        if S > self.layers:
            # composite (its cost grows with the square of the surfaces) and shade only each
            # pixel's `layers` most covering surfaces among those not hidden: behind the nearest
            # solid one (coverage > 0.999) by more than 10 gamma, a surface's weight is < 1e-3 of
            # its coverage. Ties (hard image: all hits) go to the nearest. A surface whose
            # coverage the dtype cannot resolve ranks below every other (negligible_coverage).
            a_, z_ = jax.lax.stop_gradient(cover), jax.lax.stop_gradient(z)
            solid = jnp.min(jnp.where(a_ > 0.999, z_, jnp.inf), -1, keepdims=True)
            shown = z_ <= solid + (10.0 * gamma if soft else 0.0)
            key = jnp.where(shown, a_ - 1e-6 * z_ / self.far, -1.0 - z_ / self.far)
            key = jnp.where(a_ >= negligible_coverage(r.dtype), key, -3.0)
            lay = jax.lax.top_k(key, self.layers)[1]  # (P, L)
            oh = (lay[..., None] == jnp.arange(S)).astype(r.dtype)  # (P, L, S)

            def pick(x):
                if x.shape[0] != P:  # one row per slot: a product with the one-hot rows
                    return jnp.einsum("pls,s...->pl...", oh, x.astype(r.dtype))
                return jnp.take_along_axis(x, lay.reshape(lay.shape + (1,) * (x.ndim - 2)), 1)

            cover, z, p, n, alb, mt = (pick(x) for x in (cover, z, p, n, alb, mt))
            gid = (jnp.take_along_axis(gid, lay, 1) if gid.shape[0] == P
                   else jnp.asarray(gid)[lay])
            S = self.layers
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
        if self.shadows and np.any(self.lights["castshadow"]):
            # one shadow ray per pixel, from the surface that shows most there (the hard image's
            # hit): the shadow of every geom's point at that pixel
            win = jnp.argmax(jax.lax.stop_gradient(w), -1)
            pw = jnp.take_along_axis(jax.lax.stop_gradient(p), win[:, None, None], -2)[:, 0]
            gw = gid[win] if gid.ndim == 1 else jnp.take_along_axis(gid, win[:, None], -1)[:, 0]
            for i in np.flatnonzero(self.lights["castshadow"]):
                l, dist_l, _ = self._light_dir(int(i), pw)
                lit[int(i)] = self._unoccluded(pw, l, dist_l, gw, geoms)
        col = self._shade(p, n, o, forward, alb, mt, lit)
        w_rgb, bg_rgb = composite(cover * alpha)
        rgb = jnp.sum(w_rgb[..., None] * col, -2)  # black background
        if soft:
            depth = prim.sum_last(w * z) + bg * self.far_depth
        else:
            depth = jnp.where(any_hit, jnp.min(s_hit, -1), self.far_depth)
        if oh is not None:  # back to every slot
            w = jnp.einsum("pl,pls->ps", w, oh)
        return Images(rgb=rgb.astype(r.dtype).reshape(H, W, 3), depth=depth.reshape(H, W),
                      segmentation=seg,
                      body=body, weights=self._per_geom(w, parts).reshape(H, W, G),
                      background=bg.reshape(H, W))

    # ------------------------------------------------------------------ the C++ kernel
    @functools.cached_property
    def _native_attrs(self) -> dict | None:
        """The scene as the C++ kernel (``twinrl.render.native``) takes it; None where it does
        not draw it (meshes; more than 64 geoms or surfaces a pixel)."""
        if _MESH in self.types or self.ngeom > 64 or self.surfaces() > 64 or self.layers > 64:
            return None
        L, hl = self.lights, self.headlight
        rows = [np.concatenate([[L["type"][i]], L["pos"][i], L["dir"][i], L["ambient"][i],
                                L["diffuse"][i], L["specular"][i],
                                [L["cutoff"][i], L["exponent"][i]], L["attenuation"][i],
                                [float(L["castshadow"][i])]]) for i in range(len(L["type"]))]
        return dict(
            types=np.asarray(self.types, np.int32), gids=np.asarray(self.geom_ids, np.int32),
            bodies=np.asarray(self.bodies, np.int32),
            opts=np.asarray([self.iters, self.per_pixel, self.cull_above, self.layers,
                             int(self.shadows)], np.int32),
            mat=np.stack([self.specular, self.shininess, self.emission], -1).reshape(-1),
            lights=np.concatenate(rows).astype(np.float64) if rows else np.zeros(0),
            headlight=np.concatenate([[float(hl["active"])], hl["ambient"], hl["diffuse"],
                                      hl["specular"]]).astype(np.float64))

    def _native_target(self, camera: Camera, geoms: Geoms) -> str | None:
        """The C++ kernel's FFI target for this render, or None (JAX draws it)."""
        from twinrl.render import native

        if self._native_attrs is None or not native.available():
            return None
        dt = jnp.result_type(camera.pos.dtype, geoms.xpos.dtype)
        return native.TARGETS.get(jnp.dtype(dt).name)

    def _native_inputs(self, camera: Camera, geoms: Geoms, dt):
        """The kernel's inputs: cam (15,) = position, xmat (row-major), pixel size, principal
        point; geo (G, 19) = xpos, xmat, size, albedo of the renderer's geoms."""
        xpos, xmat, size, rgba = self._select(geoms)
        cx, cy = camera._principal()
        cam = jnp.concatenate([camera.pos.astype(dt), camera.xmat.reshape(9).astype(dt),
                               jnp.stack([camera.pixel_size(), cx, cy]).astype(dt)])
        geo = jnp.concatenate([xpos, xmat.reshape(self.ngeom, 9), size, self._albedo(rgba)],
                              -1).astype(dt)
        return cam, geo

    def _native_call(self, target: str, outs, *args):
        call = jax.ffi.ffi_call(target, outs, vmap_method="broadcast_all")
        scal = np.asarray([self.near, self.far, self.far_depth], np.float64)
        return call(*args, scal=scal, **self._native_attrs)

    def _render_native(self, camera: Camera, geoms: Geoms, tg, target: str) -> Images:
        """``_render``'s values from the C++ kernel (``tg``: tau and gamma; derivatives: see
        ``_render_batched``)."""
        dt = jnp.result_type(camera.pos.dtype, geoms.xpos.dtype)
        cam, geo = self._native_inputs(camera, geoms, dt)
        G, H, W = self.ngeom, camera.height, camera.width
        sds = jax.ShapeDtypeStruct
        rgb, depth, seg, body, w, bg = self._native_call(
            target, (sds((H, W, 3), dt), sds((H, W), dt), sds((H, W), jnp.int32),
                     sds((H, W), jnp.int32), sds((H, W, G), dt), sds((H, W), dt)),
            cam, geo, jnp.asarray(tg, dt))
        return Images(rgb=rgb, depth=depth, segmentation=seg, body=body, weights=w,
                      background=bg)

    def _pullback_native(self, camera: Camera, geoms: Geoms, tg, ct: Images, target: str):
        """The cotangents of ``camera`` and ``geoms`` from those of an image (``ct``): the C++
        reverse kernel, then the packing of its inputs (``_native_inputs``) in JAX."""
        from twinrl.render import native

        dt = jnp.result_type(camera.pos.dtype, geoms.xpos.dtype)
        (cam, geo), pull = jax.vjp(lambda c, g: self._native_inputs(c, g, dt), camera, geoms)
        sds = jax.ShapeDtypeStruct
        gcam, ggeo = self._native_call(
            native.VJP_TARGETS[target], (sds(cam.shape, dt), sds(geo.shape, dt)), cam, geo,
            jnp.asarray(tg, dt), *(jnp.asarray(x, dt) for x in (ct.rgb, ct.depth, ct.weights,
                                                                 ct.background)))
        return pull((gcam, ggeo))

    def _per_geom(self, w, parts):
        """Slot weights (P, S) back to geoms (P, G), in renderer order."""
        blocks, order, a = [], [], 0
        for (t, idx), q in zip(self._groups(), parts):
            k = q[0].shape[-1]
            wk = w[:, a:a + k]
            a += k
            if self._culled(t, idx):
                oh = (q[-1][..., None] == jnp.asarray(idx)).astype(w.dtype)  # (P, K, n)
                wk = jnp.einsum("pk,pkn->pn", wk, oh)
            blocks.append(wk)
            order.extend(idx)
        out = jnp.concatenate(blocks, -1)
        if order == sorted(order):
            return out
        return out[:, np.argsort(order)]

    def _face_planes(self, geoms, xpos, xmat, idx):
        """Unit normals ``fn`` (T, 3) and offsets ``off`` (T,) of every mesh triangle's plane in
        the world, and ``sel`` (len(idx), T): which triangles belong to each mesh geom in ``idx``
        (a convex mesh's distance is its largest face-plane distance)."""
        tri = self._triangles(geoms, xpos, xmat)
        k = np.asarray(self.tri_geom)
        sel = np.stack([k == g for g in idx])
        fn = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        fn = fn / jnp.sqrt(jnp.sum(fn * fn, -1, keepdims=True) + 1e-30)
        return fn, jnp.sum(fn * tri[:, 0], -1), sel

    def _mesh_normals(self, o, r, s_hit, geoms, xpos, xmat, idx):
        """Hard normals of mesh geoms ``idx`` where the rays hit them (the face whose plane the
        hit point lies on). (..., len(idx), 3)"""
        fn, off, sel = self._face_planes(geoms, xpos, xmat, idx)
        p = o + jnp.where(jnp.isfinite(s_hit), s_hit, self.far)[..., None] * r[..., None, :]
        vals = jnp.where(sel, jnp.einsum("...gi,ti->...gt", p, fn) - off, -jnp.inf)
        return fn[jnp.argmax(vals, -1)]


BATCH_ELEMENTS = 2 ** 18
"""How many (pixel, surface) pairs a batched render (``jax.vmap`` over cameras or scenes) works
on at once, at most: a larger batch is drawn in chunks of cameras (``Renderer.batch_chunk``), so
that each operation's arrays stay in the CPU's caches. Batch 16, 2 CPU cores: peg insertion's
15 geoms (61k pairs a 64x64 frame) drawn 4 cameras at a time instead of all 16 at once, 1.3x
faster hard and soft (1.8x / 1.3x at 128x128); push's 4 geoms (16k pairs a frame) stay one batch
at 64x64 (``bench/render.py``)."""


def _render_batched(R, camera, geoms, tau, gamma, target=None):
    """``R._render``, the same function under every transformation, drawn by the C++ kernel
    where there is one (``target``, its FFI target; None: JAX), else by a ``jax.vmap`` of the
    JAX version in chunks of ``R.batch_chunk`` cameras (``lax.map``) rather than as one array
    program. Its JVP (``custom_jvp``) is ``R._render``'s, whose reverse mode is the kernel's
    reverse pass (``linear.jvp_with_pullback``: a custom VJP alone would leave ``jax.jacfwd``,
    visual Real2Sim's Jacobians, nothing to go through)."""

    static = isinstance(tau, (int, float)) and isinstance(gamma, (int, float))
    # NumPy leaves (a vmap's batched ones too, which stay NumPy inside the batch tracer) made
    # arrays: custom_jvp takes only canonical arrays
    camera, geoms = jax.tree_util.tree_map(lambda x: jnp.asarray(x) * 1, (camera, geoms))
    dt = jnp.result_type(camera.pos.dtype, geoms.xpos.dtype)
    # the temperatures travel as an argument (the kernel's input), so that a traced tau (an
    # annealed fit's) is drawn by the kernel too; a Python tau stays static for JAX (0: hard)
    tg = jnp.stack([jnp.asarray(tau, dt), jnp.asarray(gamma, dt)])

    def plain(c, g, tg):
        return R._render(c, g, tau if static else tg[0], gamma if static else tg[1])

    def primal(c, g, tg):
        return plain(c, g, tg) if target is None else R._render_native(c, g, tg, target)

    @jax.custom_batching.custom_vmap
    def chunked(c, g, tg):
        return primal(c, g, tg)

    @chunked.def_vmap
    def _rule(axis_size, in_batched, c, g, tg):
        leaves, tree = jax.tree_util.tree_flatten((c, g, tg))
        flags = tree.flatten_up_to(tuple(in_batched))
        batched = [x for x, b in zip(leaves, flags) if b]

        def one(xs):
            it = iter(xs)
            return primal(*jax.tree_util.tree_unflatten(
                tree, [next(it) if b else x for x, b in zip(leaves, flags)]))

        # the C++ kernel takes the whole batch (its rows split across the cores)
        k = axis_size if target is not None else R.batch_chunk(c.height, c.width, axis_size)
        out = (jax.vmap(one)(batched) if k >= axis_size
               else jax.lax.map(one, batched, batch_size=k))
        return out, jax.tree_util.tree_map(lambda _: True, out)

    @jax.custom_jvp
    def render(c, g, tg):
        return chunked(c, g, tg)

    def through_jax(cgt, ct):
        return jax.vjp(plain, *cgt)[1](ct)

    @jax.custom_jvp
    def pullback(cgt, ct):
        c, g, tg = cgt
        return (*R._pullback_native(c, g, tg, ct, target), jnp.zeros_like(tg))

    @pullback.defjvp
    def _pullback_jvp(primals, tangents):  # second derivatives: through JAX
        return jax.jvp(through_jax, primals, tangents)

    def _jvp(primals, tangents):
        through_kernel = target is not None and isinstance(tangents[2], SymbolicZero)
        tangents = jax.tree_util.tree_map(_instantiate, tangents,
                                          is_leaf=lambda x: isinstance(x, SymbolicZero))
        if not through_kernel:  # (or a derivative w.r.t. the temperatures: JAX has one)
            return jax.jvp(plain, primals, tangents)
        # the kernel draws the image; forward mode differentiates the JAX renderer, reverse
        # mode runs the kernel's reverse pass (``linear.jvp_with_pullback``)
        t = linear.jvp_with_pullback(lambda cgt: plain(*cgt), pullback, primals, tangents)
        return render(*primals), t  # (itself: differentiable again, e.g. a Hessian)

    render.defjvp(_jvp, symbolic_zeros=True)
    return render(camera, geoms, tg)


def _instantiate(t):
    """A symbolic zero tangent as an array (``float0`` for integer primals)."""
    if not isinstance(t, SymbolicZero):
        return t
    if t.dtype == jax.dtypes.float0:
        return np.zeros(t.shape, jax.dtypes.float0)
    return jnp.zeros(t.shape, t.dtype)


_render_jit = jax.jit(_render_batched, static_argnums=(0, 3, 4, 5))
