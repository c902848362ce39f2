"""The camera mount of the manipulation tasks (SAM-RL, Lv et al. 2023, Sec. 4: a second arm moves
an RGB-D camera), modelled by what matters for sensing: a reachable workspace (a spherical shell
patch around a look-at point: azimuth, elevation, distance ranges), a look-at constraint, and a
speed limit (``steps_to_move``). Its pose is a controllable input: ``camera(coords)`` gives a
``twinrl.render.Camera`` that is differentiable in the coordinates, which is what the
sensing-aware camera choice optimises."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True)
class CameraMount:
    """A camera carried by a second arm around a look-at point: its reachable poses are
    ``target + distance * (cos el cos az, cos el sin az, sin el)`` looking at ``target``, with
    azimuth, elevation and distance in their ranges.

    ``pose(coords)`` takes *unconstrained* coordinates (3,) mapped into the ranges by a sigmoid,
    so gradient ascent (sensing: the camera pose that maximises Q) cannot leave the workspace;
    ``coords = 0`` is the middle of every range. ``box_coords``/``coords_of`` convert from and to
    ``(azimuth rad, elevation rad, distance m)``.
    """

    target: tuple[float, float, float] = (0.5, 0.0, 0.05)
    """The look-at point (world, m)."""
    azimuth: tuple[float, float] = (-2.0, 2.0)
    """Range (rad) of the camera's direction about the vertical, from the target's +x side."""
    elevation: tuple[float, float] = (0.25, 1.35)
    """Range (rad) of the camera's height angle above the target."""
    distance: tuple[float, float] = (0.45, 0.8)
    """Range (m) of the camera's distance from the target."""
    default: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The default (fixed-camera baseline) pose's unconstrained coordinates."""
    fovy: float = 50.0
    """Vertical field of view (degrees)."""
    max_speed: float = 0.25
    """Largest move (rad of azimuth/elevation, or m of distance) the mount makes per control step:
    moving the camera costs ``steps_to_move`` time steps."""
    pos_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The camera's offset (m) from the commanded pose, in the commanded camera frame: the
    hand-eye calibration (``with_hand_eye``), zero in the nominal model. A real mount's camera
    sits where its hand-eye offset puts it (``RealTwin.move_camera``)."""
    rot_offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The camera's rotation (rotation vector, rad) from the commanded orientation, in the
    commanded camera frame: the other half of the hand-eye calibration."""

    def _ranges(self):
        return np.array([self.azimuth, self.elevation, self.distance], np.float64)

    def spherical(self, coords: jax.Array) -> jax.Array:
        """``(azimuth, elevation, distance)`` of unconstrained ``coords``."""
        r = jnp.asarray(self._ranges(), coords.dtype)
        return r[:, 0] + (r[:, 1] - r[:, 0]) * jax.nn.sigmoid(coords)

    def coords_of(self, spherical) -> np.ndarray:
        """Unconstrained coordinates of ``(azimuth, elevation, distance)`` (inside the ranges)."""
        r = self._ranges()
        u = (np.asarray(spherical, np.float64) - r[:, 0]) / (r[:, 1] - r[:, 0])
        if np.any(u <= 0) or np.any(u >= 1):
            raise ValueError(f"camera pose {spherical} is outside the mount's workspace "
                             f"azimuth {self.azimuth}, elevation {self.elevation}, "
                             f"distance {self.distance}")
        return np.log(u) - np.log1p(-u)

    def eye(self, coords: jax.Array) -> jax.Array:
        az, el, dist = self.spherical(coords)
        d = jnp.stack([jnp.cos(el) * jnp.cos(az), jnp.cos(el) * jnp.sin(az), jnp.sin(el)])
        return jnp.asarray(self.target, coords.dtype) + dist * d

    def quat(self, coords: jax.Array) -> jax.Array:
        """Camera orientation quaternion (w, x, y, z), MuJoCo's convention (looking down its -z,
        image up its +y): turned by the azimuth about the vertical and tilted down by the
        elevation, from the pose that looks along -x with the world's z up."""
        from twinrl.render import quat_mul

        az, el, _ = self.spherical(coords)
        q_az = jnp.stack([jnp.cos(az / 2), 0.0 * az, 0.0 * az, jnp.sin(az / 2)])
        q_el = jnp.stack([jnp.cos(-el / 2), 0.0 * el, jnp.sin(-el / 2), 0.0 * el])
        q0 = jnp.full(4, 0.5, coords.dtype)  # columns (y, z, x): right, up, backwards
        return quat_mul(quat_mul(q_az, q_el), q0)

    def xmat(self, coords: jax.Array) -> jax.Array:
        """Camera orientation (columns: image right, image up, backwards)."""
        from twinrl.render import quat_to_mat

        return quat_to_mat(self.quat(coords))

    def camera(self, coords: jax.Array, width: int = 64, height: int = 64):
        """The ``twinrl.render.Camera`` at ``coords`` (differentiable in them), the hand-eye
        offset (``pos_offset``, ``rot_offset``) included."""
        from twinrl.render import Camera, quat_mul, rotvec_to_quat

        coords = jnp.asarray(coords)
        eye, quat = self.eye(coords), self.quat(coords)
        if any(self.pos_offset) or any(self.rot_offset):
            dt = coords.dtype
            eye = eye + self.xmat(coords) @ jnp.asarray(self.pos_offset, dt)
            quat = quat_mul(quat, rotvec_to_quat(jnp.asarray(self.rot_offset, dt)))
        return Camera(eye, quat, jnp.asarray(self.fovy, coords.dtype), int(width), int(height))

    def with_hand_eye(self, camera, coords=None) -> "CameraMount":
        """This mount with the hand-eye offset that puts its camera at ``camera`` (a
        ``twinrl.render.Camera``, e.g. Real2Sim's fit of frames taken with the mount commanded to
        ``coords``, default ``default``): the offset of ``camera`` from the commanded pose, in the
        commanded camera frame."""
        from twinrl.render import quat_to_mat

        c = jnp.asarray(self.default if coords is None else coords, jnp.float32)
        R0 = np.asarray(self.xmat(c), np.float64)
        eye0 = np.asarray(self.eye(c), np.float64)
        R = np.asarray(quat_to_mat(jnp.asarray(camera.quat, jnp.float32)), np.float64)
        dR = R0.T @ R
        import mujoco

        q = np.empty(4)
        mujoco.mju_mat2Quat(q, dR.reshape(-1))
        rv = np.empty(3)
        mujoco.mju_quat2Vel(rv, q, 1.0)
        dp = R0.T @ (np.asarray(camera.pos, np.float64) - eye0)
        return dataclasses.replace(self, pos_offset=tuple(float(x) for x in dp),
                                   rot_offset=tuple(float(x) for x in rv))

    def calibration_poses(self, n: int) -> np.ndarray:
        """``n`` mount poses (unconstrained coordinates, ``(n, 3)``) to calibrate the hand-eye
        offset from: the default pose first, then poses spread over the middle 70 % of each
        range (a Halton sequence: deterministic, every prefix well spread). Several are needed:
        from one pose a sideways shift of the camera and a turn of it give nearly the same
        image."""
        if int(n) < 1:
            raise ValueError(f"calibration_poses: n must be >= 1, got {n}")
        out = [np.asarray(self.default, np.float64)]
        for k in range(1, int(n)):
            u = np.array([_radical_inverse(k, b) for b in (2, 3, 5)])
            out.append(self.coords_of(self._ranges()[:, 0] + (0.15 + 0.7 * u)
                                      * np.diff(self._ranges(), axis=1)[:, 0]))
        return np.stack(out)

    def steps_to_move(self, coords_from, coords_to) -> int:
        """Control steps the mount needs between two poses at its speed limit."""
        a = np.asarray(self.spherical(jnp.asarray(coords_from, jnp.float32)))
        b = np.asarray(self.spherical(jnp.asarray(coords_to, jnp.float32)))
        return int(np.ceil(np.max(np.abs(b - a)) / self.max_speed))


def _radical_inverse(k: int, base: int) -> float:
    """The ``k``-th element of van der Corput's sequence in ``base`` (Halton's coordinates)."""
    out, f = 0.0, 1.0 / base
    while k:
        k, d = divmod(k, base)
        out += d * f
        f /= base
    return out
