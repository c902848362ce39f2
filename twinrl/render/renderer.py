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
arrays stay in the CPU's caches (``batching.render_batched``; derivatives go through the whole
batch). On the CPU a C++ kernel of the same arithmetic draws the images (``twinrl.render.native``:
packets of pixels in SIMD lanes, built on first use; JAX where there is no compiler, and for
meshes), and its reverse pass gives their gradients (``jax.grad``, ``jax.vjp``); forward mode
(``jax.jvp``, ``jax.jacfwd``) and second derivatives go through this JAX version.

Everything is a pure function of ``Camera`` and ``Geoms`` pytrees: jit, vmap (batches of cameras
or scenes) and grad reach the camera pose and intrinsics, geom poses (``geom_xpos``/``geom_xmat``
of an ``mjx.Data``), ``geom_size``, ``geom_rgba`` and mesh vertices.

Modules: this one holds ``Renderer`` (what a scene's static structure is, and the entry points);
``scene`` the ``Geoms`` and ``Images`` pytrees; ``cast`` rays against geoms and the per-pixel
culling; ``shading`` lights and shadows; ``image`` the JAX renderer of one image; ``kernel`` the
calls into the C++ kernel; ``batching`` the render under ``jit``, ``vmap`` and derivatives;
``primitives`` (with ``polyhedra``) the ray geometry of each geom type.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Sequence

import jax
import mujoco
import numpy as np

from twinrl.jaxconfig import exact_matmuls
from twinrl.render import batching, cast, kernel, shading
from twinrl.render.batching import BATCH_ELEMENTS
from twinrl.render.camera import Camera
from twinrl.render.image import negligible_coverage
from twinrl.render.primitives import GEOM_NAMES, PRIMITIVES
from twinrl.render.scene import MESH, Geoms, Images, UnsupportedGeomError

__all__ = ["Geoms", "Images", "Renderer", "UnsupportedGeomError", "BATCH_ELEMENTS",
           "negligible_coverage"]


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
        Culling (``cast.choose``) keeps, per pixel, the geoms whose bounding capsule the ray passes
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
        """The renderer of ``model`` (the arguments are the class's); ``UnsupportedGeomError``
        for a geom type it cannot draw, ``ValueError`` for a geom id out of range."""
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
            if t not in PRIMITIVES and t != MESH:
                raise UnsupportedGeomError(
                    f"geom {g} ({model.geom(g).name or 'unnamed'}) has type "
                    f"{GEOM_NAMES.get(t, t)!r}; the renderer draws plane, sphere, capsule, "
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
            if model.geom_type[g] == MESH:
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
            use_mat_rgba=use_mat, lights=shading.lights(model),
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
        """How many geoms it draws."""
        return len(self.geom_ids)

    def index(self, geom_id: int) -> int:
        """Position of model geom ``geom_id`` in ``Images.weights``' last axis."""
        if geom_id not in self.geom_ids:
            raise ValueError(f"geom {geom_id} is not drawn by this renderer ({self.geom_ids})")
        return self.geom_ids.index(geom_id)

    # ------------------------------------------------------------------ structure
    def groups(self) -> list[tuple[int, np.ndarray]]:
        """The drawn geoms by primitive type: ``[(type, renderer indices)]`` (static)."""
        types = np.asarray(self.types)
        return [(t, np.flatnonzero(types == t)) for t in sorted(set(self.types))]

    def culled(self, t: int, idx) -> bool:
        """Whether geoms ``idx`` of primitive type ``t`` are culled per pixel (``per_pixel``)."""
        return t not in (0, MESH) and len(idx) > max(self.per_pixel, self.cull_above)

    def surfaces(self) -> int:
        """How many surfaces each pixel's ray is tested against (per-pixel culling included;
        a mesh counts its triangles)."""
        n = 0
        for t, idx in self.groups():
            n += (len(self.tri_geom) if t == MESH
                  else self.per_pixel if self.culled(t, idx) else len(idx))
        return n

    @functools.cached_property
    def kernel_attrs(self) -> dict | None:
        """The scene as the C++ kernel (``twinrl.render.native``) takes it; None where it does
        not draw it (meshes; more than 64 geoms or surfaces a pixel)."""
        return kernel.scene_attrs(self)

    # ------------------------------------------------------------------ ray casting
    def cast(self, o, r, geoms: Geoms, *, soft: bool = False, iters: int | None = None,
             normal_tau=None):
        """Intersect rays ``o + s r`` with every drawn geom: ``twinrl.render.cast.cast`` of this
        renderer (its returns and arguments are described there)."""
        return cast.cast(self, o, r, geoms, soft=soft, iters=iters, normal_tau=normal_tau)

    def sdf(self, points: jax.Array, geoms: Geoms) -> jax.Array:
        """Signed distance (m) of world ``points`` (..., 3) to each drawn geom's surface
        (..., G): exact for sphere, capsule, box, cylinder, plane (|z| inside its rectangle);
        approximate for ellipsoids; a convex mesh's largest face-plane distance."""
        return cast.signed_distance(self, points, geoms)

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
            return batching.render_jit(self, camera, geoms, float(tau), float(gamma),
                                       kernel.native_target(self, camera, geoms))
        return batching.render_batched(self, camera, geoms, tau, gamma,
                                       kernel.native_target(self, camera, geoms))

    def batch_chunk(self, height: int, width: int, batch: int) -> int:
        """How many cameras of a batch of ``batch`` a ``jax.vmap``-ed render draws at once: the
        largest divisor of ``batch`` whose (pixel, surface) pairs stay within
        ``BATCH_ELEMENTS`` (a divisor, so that ``lax.map`` compiles one chunk and no
        remainder)."""
        return batching.batch_chunk(self, height, width, batch)
