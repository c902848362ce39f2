"""What the renderer draws and what it gives back: ``Geoms`` (the scene's geoms, from an MJX or
MuJoCo model and data) and ``Images`` (a rendered frame), and the error for a geom it cannot draw.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import mujoco

MESH = 7
"""``mjtGeom`` of a mesh (drawn through its triangles, never culled)."""


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
            data = jitted_kinematics()(model, data)
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
        """A copy with the fields in ``kw`` replaced."""
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


@functools.cache
def jitted_kinematics():
    """``mjx.kinematics`` jitted (what ``Geoms.from_mjx`` runs): inside an outer trace, one
    equation whose trace (and its derivatives and batched forms) every render of a model's state
    reuses -- tracing MJX's kinematics of the arm takes seconds, and a camera ascent renders the
    same state twice."""
    from mujoco import mjx

    return jax.jit(mjx.kinematics)
