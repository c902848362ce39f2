"""Visual Real2Sim: fit the simulator's camera and objects to real RGB-D + segmentation frames.

SAM-RL (Lv et al., 2023), Sec. 3.2: the real robot's camera images are compared with images the
differentiable renderer (``twinrl.render``) draws of the simulated scene, and gradient descent on
the difference updates (a) the camera extrinsics, given a known scene; (b) an object's pose, size
and colour, given a known camera; (c) the vertices of a mesh object (regularised by edge lengths
and a Laplacian, so the surface stays smooth). The loss is a weighted sum of

- ``rgb``: mean squared RGB difference (soft image, SoftRas Sec. 3.3, so edges give gradients);
- ``iou``: 1 - soft IoU of the geoms' masks with the real segmentation;
- ``emd``: Sinkhorn EMD between the real depth's point cloud and the rendered one (the object's
  points in (b)/(c); every geom's in (a)); the real points are unprojected with the *current*
  camera estimate, so a wrong camera shows as misplaced surfaces;
- ``depth``: mean absolute depth difference over pixels where the real camera sees a geom;
- ``surface``: mean squared distance of the real depth points to the surfaces of the geoms the
  real segmentation assigns them (a point-to-model, ICP-like term: it still pulls when a
  silhouette is many pixels off and the soft masks no longer overlap).

The temperature of the soft silhouette is annealed from coarse to fine; several random restarts
are run and the best (lowest final loss) kept.

Frames come from a dataset recorded by ``twinrl collect --images`` (states read back from the
observations; see ``state_from_obs``) or as a list of dicts with ``rgb`` (H, W, 3) uint8,
``depth`` (H, W) metres, ``segmentation`` (H, W) geom ids and ``qpos``. The entry point is
``visual_sysid``.

The package, by concern: ``config`` (``VisualConfig``), ``frames`` (reading, checking and
preparing frames), ``losses`` (the loss terms and the refinement's residuals), ``solvers`` (Adam
over restarts, Levenberg-Marquardt), ``fits`` (the camera, object, mesh and body fits) and
``command`` (``visual_sysid``).
"""

from __future__ import annotations

from twinrl.real2sim.visual.command import DEFAULT_OBJECT, visual_sysid
from twinrl.real2sim.visual.config import VisualConfig
from twinrl.real2sim.visual.fits import (body_geoms, fit_body_offset, fit_camera, fit_mesh,
                                         fit_object)
from twinrl.real2sim.visual.frames import check_frames, frames_from_dataset, state_from_obs

__all__ = ["VisualConfig", "visual_sysid", "fit_camera", "fit_object", "fit_mesh",
           "fit_body_offset", "body_geoms",
           "state_from_obs", "frames_from_dataset", "check_frames", "DEFAULT_OBJECT"]
