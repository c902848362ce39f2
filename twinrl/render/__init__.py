"""Differentiable rendering of MJX scenes (SAM-RL, Sec. 3.2; SoftRas soft silhouettes).

``Camera`` (pose + pinhole intrinsics pytree, MuJoCo's convention), ``Renderer`` (ray casting of
an MJX scene's geoms to RGB, depth, segmentation and soft masks), ``Geoms`` (what it draws, from an
``mjx.Data``), point clouds and their losses (``pointcloud``: Chamfer and Sinkhorn EMD).
"""

from twinrl.render.camera import Camera, look_at, quat_mul, quat_to_mat, rotvec_to_quat
from twinrl.render.renderer import Geoms, Images, Renderer, UnsupportedGeomError

__all__ = ["Camera", "look_at", "quat_mul", "quat_to_mat", "rotvec_to_quat", "Geoms", "Images",
           "Renderer", "UnsupportedGeomError"]
