"""``Camera``: a pinhole camera as a JAX pytree, in MuJoCo's convention.

SAM-RL (Lv et al., 2023), Sec. 3.2 optimises the camera pose through a differentiable renderer;
this is the camera of that renderer. Its pose (``pos``, ``quat``) and field of view (``fovy``) are
arrays, so ``jax.grad`` reaches them; the image size is static (a pytree auxiliary field).

Convention (MuJoCo's, so images line up with ``mujoco.Renderer``'s):
  - the camera frame's columns are x = image right, y = image up, z = *backwards*: the camera looks
    along -z (``data.cam_xmat`` reshaped (3, 3) is that frame in world coordinates);
  - ``fovy`` is the full vertical field of view in degrees; pixels are square, so the horizontal
    extent is ``tan(fovy / 2) * width / height`` at unit depth;
  - image row 0 is the *top* of the picture (as ``mujoco.Renderer.render`` returns it), pixel
    centres are at half-integers;
  - the optical axis meets the image at ``principal`` (column, row, in pixels), by default the
    image's centre (MuJoCo's cameras); ``Camera.window`` uses it to make a camera that sees a
    window of another's pixels, or every k-th of them, exactly;
  - depth is the distance along the viewing axis (-z), not along the ray.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.physics.rotations import mat_to_quat, quat_mul, quat_to_mat, rotvec_to_quat

__all__ = ["Camera", "quat_to_mat", "mat_to_quat", "quat_mul", "rotvec_to_quat", "look_at"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Camera:
    """A pinhole camera. ``pos`` (3,), ``quat`` (4,) ``(w, x, y, z)`` of the camera frame in the
    world (need not be unit: it is normalised where used), ``fovy`` () degrees (the focal length
    is ``height / (2 tan(fovy / 2))`` pixels); ``principal`` (2,) the (column, row) in pixels
    where the optical axis meets the image, ``None`` for the image's centre; ``width`` and
    ``height`` are static. A batch of cameras is a ``Camera`` whose arrays have a leading axis
    (``jax.vmap`` over it)."""

    pos: jax.Array
    quat: jax.Array
    fovy: jax.Array
    width: int = dataclasses.field(metadata=dict(static=True), default=64)
    height: int = dataclasses.field(metadata=dict(static=True), default=64)
    principal: jax.Array | None = None

    # ------------------------------------------------------------------ construction
    @classmethod
    def create(cls, pos, quat=None, *, xmat=None, fovy=45.0, width: int = 64,
               height: int = 64, principal=None, dtype=None) -> "Camera":
        """A camera from a position and either a quaternion or a rotation matrix (camera frame
        columns in world coordinates); ``principal`` (column, row) in pixels, default the
        image's centre."""
        if (quat is None) == (xmat is None):
            raise ValueError("give exactly one of quat and xmat")
        if int(width) < 1 or int(height) < 1:
            raise ValueError(f"image size must be >= 1x1, got {width}x{height}")
        if quat is None:
            xmat = np.asarray(xmat, np.float64)
            if xmat.size != 9:
                raise ValueError(f"xmat must have 9 entries (3x3), got shape {xmat.shape}")
            quat = mat_to_quat(xmat)
        pos = np.asarray(pos, np.float64)
        quat = np.asarray(quat, np.float64)
        if pos.shape != (3,) or quat.shape != (4,):
            raise ValueError(f"pos must be (3,) and quat (4,), got {pos.shape} and {quat.shape}")
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))
                and np.linalg.norm(quat) > 0):
            raise ValueError(f"camera pose must be finite with a non-zero quaternion, got "
                             f"pos={pos}, quat={quat}")
        if not 0.0 < float(fovy) < 180.0:
            raise ValueError(f"fovy must be in (0, 180) degrees, got {fovy}")
        dtype = dtype or jnp.result_type(float)
        if principal is not None:
            principal = np.asarray(principal, np.float64)
            if principal.shape != (2,) or not np.all(np.isfinite(principal)):
                raise ValueError(f"principal must be a finite (column, row), got {principal}")
            principal = jnp.asarray(principal, dtype)
        return cls(jnp.asarray(pos, dtype), jnp.asarray(quat / np.linalg.norm(quat), dtype),
                   jnp.asarray(float(fovy), dtype), int(width), int(height), principal)

    @classmethod
    def from_mujoco(cls, model, data, cam_id: int | str, width: int = 64, height: int = 64,
                    dtype=None) -> "Camera":
        """The camera ``cam_id`` (index or name) of a ``mujoco.MjModel``/``MjData`` (after
        ``mj_forward`` or ``mj_kinematics`` + ``mj_camlight``), posed as MuJoCo renders it."""
        import mujoco

        if isinstance(cam_id, str):
            name = cam_id
            cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
            if cam_id < 0:
                raise ValueError(f"camera {name!r} is not in the model; cameras: "
                                 f"{[model.camera(i).name for i in range(model.ncam)]}")
        if not 0 <= int(cam_id) < model.ncam:
            raise ValueError(f"cam_id must be in [0, {model.ncam}), got {cam_id}")
        return cls.create(np.asarray(data.cam_xpos[cam_id]),
                          xmat=np.asarray(data.cam_xmat[cam_id]).reshape(3, 3),
                          fovy=float(model.cam_fovy[cam_id]), width=width, height=height,
                          dtype=dtype)

    # ------------------------------------------------------------------ geometry
    @property
    def xmat(self) -> jax.Array:
        """(3, 3) camera frame in world coordinates (columns: right, up, backwards)."""
        return quat_to_mat(self.quat)

    def rotated(self, rotvec: jax.Array) -> "Camera":
        """This camera turned by the axis-angle ``rotvec`` (rad) about its *own* axes, as
        ``Perturbation.camera_rot_offset`` turns MuJoCo's cameras."""
        return dataclasses.replace(self, quat=quat_mul(self.quat, rotvec_to_quat(rotvec)))

    def translated(self, delta: jax.Array) -> "Camera":
        """This camera moved by ``delta`` (m, world frame)."""
        return dataclasses.replace(self, pos=self.pos + delta)

    def pixel_size(self) -> jax.Array:
        """Height (m) of one pixel at unit depth (the inverse of the focal length in pixels)."""
        return 2.0 * jnp.tan(jnp.deg2rad(self.fovy) / 2.0) / self.height

    def principal_point(self) -> tuple[jax.Array, jax.Array]:
        """``(cx, cy)``: the principal point in pixels (the image centre unless ``principal`` is
        set)."""
        if self.principal is None:
            return (jnp.asarray(self.width / 2.0, self.pos.dtype),
                    jnp.asarray(self.height / 2.0, self.pos.dtype))
        return self.principal[..., 0], self.principal[..., 1]  # a stack of cameras too

    def rays(self) -> tuple[jax.Array, jax.Array]:
        """``origin`` (3,) and per-pixel directions (H, W, 3) in the world frame, scaled so the
        component along the viewing axis is 1: ``origin + s * dir`` is at depth ``s``."""
        H, W = self.height, self.width
        px, (cx, cy) = self.pixel_size(), self.principal_point()
        x = (jnp.arange(W, dtype=self.pos.dtype) + 0.5 - cx) * px
        y = (cy - jnp.arange(H, dtype=self.pos.dtype) - 0.5) * px
        x, y = jnp.broadcast_to(x[None, :], (H, W)), jnp.broadcast_to(y[:, None], (H, W))
        local = jnp.stack([x, y, -jnp.ones_like(x)], -1)
        return self.pos, local @ self.xmat.T

    def project(self, points: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Pixel coordinates ``(col, row)`` (..., 2) (continuous; pixel centres at +0.5) and depth
        (...,) of world points."""
        p = (points - self.pos) @ self.xmat
        depth = -p[..., 2]
        px, (cx, cy) = self.pixel_size(), self.principal_point()
        col = cx + p[..., 0] / depth / px
        row = cy - p[..., 1] / depth / px
        return jnp.stack([col, row], -1), depth

    def window(self, row0: int, col0: int, height: int, width: int, step: int = 1) -> "Camera":
        """The camera whose pixel ``(r, c)`` is this camera's pixel ``(row0 + step r,
        col0 + step c)`` (same ray through the same pixel centre), ``height`` x ``width`` of them:
        a crop (``step`` 1), every ``step``-th pixel (a coarser image of exactly those pixels), or
        both. Slice an image the same way with ``image[row0:row0 + step * height:step,
        col0:col0 + step * width:step]``. Differentiable in the pose and ``fovy``."""
        row0, col0, height, width, step = (int(a) for a in (row0, col0, height, width, step))
        if step < 1 or height < 1 or width < 1:
            raise ValueError(f"window: height, width and step must be >= 1, got "
                             f"{height}, {width}, {step}")
        if not (0 <= row0 and row0 + step * (height - 1) < self.height and 0 <= col0
                and col0 + step * (width - 1) < self.width):
            raise ValueError(f"window: rows {row0}+{step}*[0, {height}) or columns "
                             f"{col0}+{step}*[0, {width}) leave the {self.height}x{self.width} "
                             "image")
        cx, cy = self.principal_point()
        # new pixel c's centre c + 0.5 sits at old col0 + step c + 0.5; focal length / step
        principal = jnp.stack([(cx - col0 - 0.5) / step + 0.5, (cy - row0 - 0.5) / step + 0.5],
                              -1)
        # a stack of cameras (a leading axis on every array) gets one principal point each
        principal = jnp.broadcast_to(principal, jnp.shape(self.pos)[:-1] + (2,))
        fovy = 2.0 * jnp.rad2deg(jnp.arctan(jnp.tan(jnp.deg2rad(self.fovy) / 2.0)
                                            * step * height / self.height))
        return dataclasses.replace(self, fovy=fovy, width=width, height=height,
                                   principal=principal.astype(self.pos.dtype))


def look_at(eye, target, up=(0.0, 0.0, 1.0), *, fovy=45.0, width: int = 64, height: int = 64,
            dtype=None) -> Camera:
    """A camera at ``eye`` looking at ``target`` with ``up`` pointing up in the image."""
    eye, target, up = (np.asarray(a, np.float64) for a in (eye, target, up))
    back = eye - target
    if np.linalg.norm(back) == 0:
        raise ValueError("look_at: eye and target coincide")
    back = back / np.linalg.norm(back)
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-9:
        raise ValueError(f"look_at: up {up} is parallel to the viewing direction")
    right /= np.linalg.norm(right)
    cam_up = np.cross(back, right)
    return Camera.create(eye, xmat=np.stack([right, cam_up, back], 1), fovy=fovy,
                         width=width, height=height, dtype=dtype)
