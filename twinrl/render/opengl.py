"""OpenGL images of a MuJoCo model: ``CameraRenderer`` (RGB, metric depth, geom segmentation).

Both sides of the loop draw with it: the real twin's camera (``twinrl.real.twin``) and the
simulator's videos (``twinrl.learn.runner``, ``twinrl.loop``: the states are MJX's, only the pixels
come from OpenGL), and it is the reference the differentiable ``Renderer`` is tested against
(``render_states``). It lives in ``render`` so the simulator side need not import the real twin.
Not differentiable: for gradients through images use ``twinrl.render.Renderer``.

Headless: ``MUJOCO_GL=egl`` is set before MuJoCo is imported; if MuJoCo was imported first,
``select_gl_backend`` probes EGL, then OSMesa, and points MuJoCo's context at the first that starts.
"""

from __future__ import annotations

import os

# MuJoCo reads MUJOCO_GL when it is first imported; this only takes effect if nothing imported it
# before, and ``select_gl_backend`` covers the rest.
os.environ.setdefault("MUJOCO_GL", "egl")

import atexit  # noqa: E402
import importlib  # noqa: E402
import weakref  # noqa: E402
from typing import Sequence  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

__all__ = ["CameraRenderer", "render_states", "select_gl_backend", "IMAGE_KINDS"]

IMAGE_KINDS = ("rgb", "depth", "segmentation")


def select_gl_backend() -> str:
    """Make ``mujoco.Renderer`` use a headless backend: EGL, else OSMesa.

    If ``MUJOCO_GL`` was unset or ``egl`` when mujoco was imported, MuJoCo chose GLFW (needs a
    display) or EGL; we probe EGL, then OSMesa, and point MuJoCo's context class at the first
    that starts (what setting ``MUJOCO_GL`` before the import would have done). Any other value
    the user chose is respected.
    """
    from mujoco.rendering.classic import gl_context

    requested = getattr(gl_context, "_MUJOCO_GL", "")
    if requested not in ("", "egl"):
        return requested
    errors = []
    for backend in ("egl", "osmesa"):
        try:
            cls = importlib.import_module(f"mujoco.{backend}").GLContext
            probe = cls(1, 1)
            probe.free()
        except Exception as e:  # noqa: BLE001 - any failure means "try the next backend"
            errors.append(f"{backend}: {type(e).__name__}: {e}")
            continue
        gl_context.GLContext = cls
        os.environ["MUJOCO_GL"] = backend
        return backend
    raise RuntimeError(
        "no headless OpenGL backend for mujoco.Renderer could start ("
        + "; ".join(errors)
        + "); install EGL or OSMesa libraries"
    )


class CameraRenderer:
    """RGB, metric depth and geom segmentation of a ``mujoco.MjModel`` from its named cameras."""

    def __init__(self, model: mujoco.MjModel, width: int = 320, height: int = 240, *,
                 shadows: bool = True, shadow_size: int | None = None):
        offw, offh = model.vis.global_.offwidth, model.vis.global_.offheight
        if not (0 < width <= offw and 0 < height <= offh):
            raise ValueError(
                f"image size {width}x{height} must be positive and within the "
                f"model's offscreen buffer {offw}x{offh}"
            )
        self.backend = select_gl_backend()
        self.model = model
        # Shadow mapping (MuJoCo's default). Without a GPU (software OpenGL) drawing the shadow
        # map is most of a frame's cost, and it is drawn at the model's <quality shadowsize>
        # (MuJoCo's default 4096^2; the arm scenes set 2048^2) whatever the image's size.
        # ``shadow_size`` (default: 4x the image's longer side, at least 1024, at most the
        # model's) sizes it to the image: measured on this project's 2-core machine (llvmpipe),
        # a 64x64 RGB frame of pendulum took 48 ms at its 4096 and 9 ms at 1024, of peg
        # insertion 24 ms at its 2048 and 13 ms at 1024, with the same mean pixel value to 0.01
        # of 255. The size is read when the OpenGL context is made; the model is left as it was.
        self.shadows = bool(shadows)
        own = int(model.vis.quality.shadowsize)
        self.shadow_size = int(shadow_size) if shadow_size is not None else min(
            own, max(1024, 4 * max(int(width), int(height))))
        if self.shadow_size < 1:
            raise ValueError(f"shadow_size must be >= 1, got {shadow_size}")
        model.vis.quality.shadowsize = self.shadow_size
        try:
            self._renderer = mujoco.Renderer(model, height, width)
        finally:
            model.vis.quality.shadowsize = own
        # A renderer never closed is closed at exit, before EGL's display is terminated (MuJoCo
        # registers that at its first context; exit functions run last-registered first). Left
        # to MuJoCo's __del__ at shutdown, the context outlives the EGL module it needs and a
        # script that never closed its twin ends on "Exception ignored" tracebacks.
        self._at_exit = _closer(weakref.ref(self))
        atexit.register(self._at_exit)

    def images(
        self, data: mujoco.MjData, camera: str | int, kinds: Sequence[str] = IMAGE_KINDS
    ) -> dict[str, np.ndarray]:
        """``rgb`` (H, W, 3) uint8, ``depth`` (H, W) float32 metres, ``segmentation`` (H, W)
        int32 geom ids (-1: no geom) of ``data`` seen from ``camera``."""
        unknown = set(kinds) - set(IMAGE_KINDS)
        if unknown:
            raise ValueError(f"unknown image kind(s) {sorted(unknown)}; allowed: {IMAGE_KINDS}")
        if (
            isinstance(camera, str)
            and mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera) < 0
        ):
            raise ValueError(
                f"camera {camera!r} is not in the scene; cameras: "
                f"{[self.model.camera(i).name for i in range(self.model.ncam)]}"
            )
        r, out = self._renderer, {}
        for kind in kinds:
            r.disable_depth_rendering()
            r.disable_segmentation_rendering()
            if kind == "depth":
                r.enable_depth_rendering()
            elif kind == "segmentation":
                r.enable_segmentation_rendering()
            r.update_scene(data, camera=camera)
            r.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.shadows
            img = r.render()
            if kind == "depth":
                img = img.astype(np.float32)
            elif kind == "segmentation":
                img = np.where(img[..., 1] == mujoco.mjtObj.mjOBJ_GEOM, img[..., 0], -1)
                img = img.astype(np.int32)
            out[kind] = img.copy()
        r.disable_depth_rendering()
        r.disable_segmentation_rendering()
        return out

    def close(self) -> None:
        atexit.unregister(self._at_exit)
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def __del__(self):  # collected unclosed: MuJoCo's own __del__ frees the context
        at_exit = getattr(self, "_at_exit", None)
        if at_exit is not None:
            atexit.unregister(at_exit)


def _closer(ref):
    def close():
        r = ref()
        if r is not None:
            r.close()
    return close


def render_states(model: mujoco.MjModel, camera: str | int, qposes: Sequence[np.ndarray],
                  width: int, height: int) -> list[dict[str, np.ndarray]]:
    """OpenGL frames (``rgb``, ``depth``, ``segmentation``, and the ``qpos`` drawn) of ``model`` at
    each of ``qposes``, from ``camera``: reference images for the differentiable renderer."""
    r = CameraRenderer(model, width, height)
    d = mujoco.MjData(model)
    frames = []
    try:
        for q in qposes:
            d.qpos[:] = q
            mujoco.mj_forward(model, d)
            frames.append({**r.images(d, camera), "qpos": np.array(q)})
    finally:
        r.close()
    return frames
