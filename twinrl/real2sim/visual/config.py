"""Settings of a visual fit (``VisualConfig``): the loss weights, the Adam stage's steps and
restarts, the soft silhouette's annealed temperature and the geometric refinement's iterations."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class VisualConfig:
    """Settings of a visual fit."""

    steps: int = 150
    """Adam steps per restart."""
    restarts: int = 3
    """Random restarts (the first starts at the nominal values); the lowest final loss wins."""
    lr: float = 4e-3
    """Adam learning rate (metres, radians, log-scale and colour-logit units alike)."""
    tau: tuple[float, float] = (1.5, 0.3)
    """Soft-silhouette temperature in pixels, annealed geometrically from first to second."""
    gamma: float = 0.01
    """Depth-order temperature (m) of the soft composite."""
    w_rgb: float = 1.0
    """Weight of the RGB L2 term."""
    w_iou: float = 0.5
    """Weight of the 1 - soft mask IoU term."""
    w_emd: float = 20.0
    """Weight of the point-cloud Sinkhorn EMD term (m^2)."""
    w_depth: float = 5.0
    """Weight of the mean absolute depth term (m)."""
    w_surface: float = 2000.0
    """Weight of the point-to-model term (m^2): mean squared signed distance of each real depth
    point (unprojected with the current camera) to the surface of the geom the real segmentation
    assigns it; long-range where silhouettes no longer overlap (ICP-like)."""
    emd_points: int = 96
    """Points per cloud in the EMD term (fixed random pixels)."""
    emd_epsilon: float = 1e-4
    """Sinkhorn regularisation (m^2)."""
    init_pos_sd: float = 0.02
    """Standard deviation (m) of the restarts' initial position offsets."""
    init_rot_sd: float = 0.03
    """Standard deviation (rad) of the restarts' initial rotation offsets."""
    mesh_smooth: float = 1.0
    """Weight of the mesh regulariser (edge-length change and Laplacian) in (c)."""
    refine_iters: int = 30
    """Levenberg-Marquardt iterations of the geometric refinement that follows Adam in (a) and
    (b) (0: none). Its residuals are metric: each real depth point's signed distance to the geom
    the real segmentation assigns it, and in (b) how deep the rays of pixels the object does not
    own pass inside it (free space), with a Huber loss; in (b) also the soft silhouette against the
    real mask (so edges sit midway between labelled and unlabelled pixel centres) and, after the
    geometry, the colour (robust, on the object's own pixels)."""
    huber: float = 0.005
    """Huber scale (m) of the refinement's residuals."""
    keep_support: bool = True
    """(b): keep the object's lowest point at the height the frames' states put it (an object
    resting on a table). Its underside is hidden, so from images alone its height trades against
    its size; a resting object's support is known."""
    coarse_size: int = 64
    """Longest side (pixels) of the images the Adam stage of (a), (b) and (c) sees: larger frames
    are subsampled by an integer step, keeping exactly the pixels a camera that many times coarser
    would see (``Camera.window``). The refinement uses every pixel: edges are placed to a finer
    pixel, and the Adam stage's cost does not grow with the resolution."""
    roi_margin: int = 6
    """(b): the refinement sees, in each frame, a window around the object's real pixels grown by
    this many pixels of the coarse image on every side (it must cover the Adam stage's error)."""

    def __post_init__(self):
        if self.steps < 1 or self.restarts < 1 or self.refine_iters < 0:
            raise ValueError(f"steps and restarts must be >= 1 and refine_iters >= 0, got "
                             f"{self.steps}, {self.restarts}, {self.refine_iters}")
        if self.coarse_size < 8 or self.roi_margin < 1:
            raise ValueError(f"coarse_size must be >= 8 and roi_margin >= 1, got "
                             f"{self.coarse_size}, {self.roi_margin}")
        if not (self.tau[0] > 0 and self.tau[1] > 0):
            raise ValueError(f"tau must be two positive temperatures (pixels), got {self.tau}")
        for f in ("w_rgb", "w_iou", "w_emd", "w_depth", "w_surface", "mesh_smooth"):
            if getattr(self, f) < 0:
                raise ValueError(f"{f} must be >= 0, got {getattr(self, f)}")
