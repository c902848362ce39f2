"""What the manipulation tasks see: renders from the camera mount, the image observation a robot
has (joints, the commanded camera pose, RGB-D and the target's mask, the target's point cloud), and
model-based perception -- the target's pose fitted to one depth image (``fit_target_pose``).

``ArmPerception`` is the image side of ``ArmTask`` (a base class of it); ``target_cloud`` is the
target's point-cloud summary that observation carries."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from twinrl.jaxconfig import exact_matmuls
from twinrl.envs.arm.kinematics import N_JOINTS


def target_cloud(camera, depth: jax.Array, mask: jax.Array) -> jax.Array:
    """What the depth image says of the target, in the world frame: the mean (3,) and spread
    (3,) of its pixels' back-projected points, seen from ``camera`` (the pose the robot
    commanded), and ``log(1 + its pixel count)`` -- 7 numbers, 0 where it is not seen. Soft and
    differentiable in the pose with a soft ``mask``."""
    from twinrl.render.pointcloud import depth_to_points

    pts, w = depth_to_points(camera, depth, mask)
    n = jnp.sum(w)
    safe = jnp.maximum(n, 1e-3)
    mean = jnp.sum(w[:, None] * pts, axis=0) / safe
    spread = jnp.sqrt(jnp.sum(w[:, None] * jnp.square(pts - mean), axis=0) / safe + 1e-10)
    return jnp.concatenate([mean, spread, jnp.log1p(n)[None]]).astype(jnp.float32)

class ArmPerception:
    """The image side of an arm task (``ArmTask`` inherits it): renders of the scene from the
    mount, the image observation, and the fit of the target's pose to a depth image.

    It reads the task's ``sim``, ``params``, ``config`` (``image_size``, ``pose_hinge_grid``),
    ``mount``, ``tool_point``, ``observe`` and ``state_from_obs``, and the target's description
    below (set by each task)."""

    target_geoms: tuple[str, ...] = ()
    """Geoms whose pose the camera must reveal (the hole's fixture, the pancake, the needle's eye):
    what ``bench/manipulation.py`` counts to say from how much of the mount's workspace the target
    is visible."""
    target_joints: tuple[int, ...] = ()
    """``qpos`` indices of the joints that place the target (``fit_target_pose`` estimates them
    from an image); () where its pose is not estimated."""
    target_hinge_period: float = np.pi
    """The turn about a target hinge after which the target looks the same (the needle's eye, a
    rectangular ring: half a turn); ``fit_target_pose`` reports hinge angles modulo it."""

    @functools.cached_property
    def renderer(self):
        """The differentiable renderer of this task's scene (``twinrl.render.Renderer``)."""
        from twinrl.render import Renderer

        return Renderer.create(self.sim.mj_model, shadows=False)

    def render(self, state, coords: jax.Array | None = None, *, tau: float = 0.0,
               size: int | None = None):
        """``twinrl.render.Images`` of ``state`` from the mount camera at ``coords``
        (unconstrained mount coordinates, default ``mount.default``): RGB, depth, segmentation,
        and soft coverage when ``tau > 0``. Differentiable w.r.t. ``coords`` and the state."""
        from twinrl.render import Geoms

        coords = jnp.asarray(self.mount.default if coords is None else coords, jnp.float32)
        n = int(size or self.config.image_size)
        cam = self.mount.camera(coords, n, n)
        data = state.pipeline_state if hasattr(state, "pipeline_state") else state
        model = self.sim.model_with(self.params)
        return self.renderer.render(cam, Geoms.from_mjx(model, data), tau=tau)

    def image_observation(self, state, coords: jax.Array | None = None, *, size: int | None = None,
                          tau: float = 0.0, keys=None) -> dict:
        """What a robot has (``observation_from_image``) when the simulator renders ``state`` from
        the mount at ``coords``: the target mask is the target geoms' share of each pixel (the
        renderer's coverage: the hard 0/1 mask at ``tau == 0``, soft and differentiable in the
        pose at ``tau > 0``). The image actor's and the sensing Q's observation
        (``twinrl.learn.imitation``, ``twinrl.learn.sensing``). ``keys``: only these entries
        (``observation_from_image``)."""
        coords = jnp.asarray(self.mount.default if coords is None else coords, jnp.float32)
        img = self.render(state, coords, tau=tau, size=size)
        mask = jnp.sum(img.weights[..., self._target_columns], axis=-1)
        return self.observation_from_image(state.obs[:2 * N_JOINTS], coords, img.rgb, img.depth,
                                           mask, keys=keys)

    def observation_from_image(self, joints, coords, rgb, depth, mask, keys=None) -> dict:
        """The image observation's layout, one for the simulator's renders and the real camera's
        frames (``twinrl.sim2real.active``): ``{"state": joint angles and velocities (14,),
        "camera": the commanded pose as fractions (3,) of the mount's azimuth, elevation and
        distance ranges (bounded, so an ascent of Q cannot push a network's input outside what it
        was trained on), "pixels/mount": (n, n, 5) RGB, depth (m) and the target's mask, "tool":
        the tool point (``tool_pose``) of the measured joints (3,), "target":
        ``target_cloud`` of the depth and mask, back-projected from the commanded pose (7,),
        "reach": the target cloud's mean minus the tool point (3,; 0 where the target is not
        seen),
        "pose": the target's joints fitted to that cloud (``fit_target_pose``) and "estimate":
        the privileged observation of the state they and the joints give (``estimated_state``;
        the tool at the identified grasp: ``observe(..., nominal=False)``)
        and "support": how much the fit stands on (2,): log(1 + target pixels) and the fit's RMS
        distance (mm) of those pixels' points from the fitted surfaces (the last three for tasks
        with ``target_joints`` only)}``. The camera is the mount's, hand-eye
        calibration included. ``keys``: only these entries, and only their work traced (the pose
        fit is most of it); default all."""
        n = depth.shape[0]
        pixels = jnp.concatenate([rgb, depth[..., None], mask[..., None]], axis=-1)
        cam = self.mount.camera(coords, n, n)
        tool, cloud = self.tool_point(joints[:N_JOINTS]), target_cloud(cam, depth, mask)
        out = {"state": joints, "camera": jax.nn.sigmoid(coords), "pixels/mount": pixels,
               "tool": tool, "target": cloud,
               "reach": jnp.where(cloud[6] > 0, cloud[:3] - tool, 0.0)}
        fitted = ("pose", "estimate", "support")
        if self.target_joints and (keys is None or any(k in keys for k in fitted)):
            pose, rms = self.fit_target_pose(joints, cam, depth, mask, with_residual=True,
                                             hinge_grid=int(self.config.pose_hinge_grid))
            out["pose"] = pose
            out["estimate"] = self.pose_estimate(joints, pose)
            out["support"] = jnp.stack([out["target"][6], 1e3 * rms])  # the cloud's count
        if keys is None:
            return out
        missing = [k for k in keys if k not in out]
        if missing:
            raise KeyError(f"{self.name}'s image observation has no {missing}; it has "
                           f"{sorted(out)}")
        return {k: out[k] for k in keys}

    def estimated_state(self, joints, pose):
        """``(qpos, qvel)`` of the measured arm (``joints``: 7 angles, 7 velocities) and the
        target at its fitted ``pose`` (``qpos[target_joints]``; at rest): the state estimate
        a robot has from its encoders and one image, whose ``observe`` is laid out as the
        privileged observation a state policy acts on."""
        dt = joints.dtype
        qpos = jnp.asarray(self.sim.mj_model.qpos0, dt).at[:N_JOINTS].set(joints[:N_JOINTS])
        qpos = qpos.at[np.asarray(self.target_joints)].set(pose)
        qvel = jnp.zeros(self.sim.nv, dt).at[:N_JOINTS].set(joints[N_JOINTS:2 * N_JOINTS])
        return qpos, qvel

    @functools.cached_property
    def _target_hinges(self) -> np.ndarray:
        """Which of ``target_joints`` are hinges (the others slide)."""
        m = self.sim.mj_model
        idx = np.asarray(self.target_joints)
        return np.asarray(m.jnt_type)[np.searchsorted(np.asarray(m.jnt_qposadr), idx)] == 3

    def _wrap_target_pose(self, pose):
        """The target's hinge angles modulo its symmetry (``target_hinge_period``), into
        (-period/2, period/2]: the pose an image can tell."""
        period = jnp.asarray(self.target_hinge_period, pose.dtype)
        return jnp.where(self._target_hinges, pose - period * jnp.round(pose / period), pose)

    def estimate_from_obs(self, obs):
        """The image observation's ``"estimate"`` under perfect perception: the privileged
        observation of the state the measured joints (``obs[:14]``) and the target's true pose
        (``state_from_obs``; at rest, hinges modulo the target's symmetry) give -- what a
        ``"pose"`` actor reads when ``fit_target_pose`` is exact. The residual policy of the
        manipulation loop is trained through a model on it (``twinrl.loop.arm``), which renders
        no images. One observation (``obs`` of shape ``(observation_size,)``)."""
        if not self.target_joints:
            raise ValueError(f"{self.name} has no target_joints: no pose estimate")
        obs = jnp.asarray(obs, jnp.float32)
        pose = self.state_from_obs(obs)[0][np.asarray(self.target_joints)]
        return self.pose_estimate(obs[:2 * N_JOINTS], self._wrap_target_pose(pose))

    def pose_estimate(self, joints, pose):
        """The image observation's ``"estimate"`` of measured ``joints`` (7 angles, 7 velocities)
        and a target ``pose``: the privileged observation (``observe``, the tool at the
        identified grasp) of their ``estimated_state`` -- what a ``"pose"`` actor reads, from
        each frame's fit, a fit kept over the episode (``twinrl.sim2real.active.PoseMemory``) or
        the true pose (``estimate_from_obs``)."""
        return self.observe(*self.estimated_state(joints, pose), nominal=False)

    @exact_matmuls
    def fit_target_pose(self, joints, camera, depth, mask, iters: int = 8,
                        huber: float = 0.004, points: int = 256, with_residual: bool = False,
                        hinge_grid: int = 0):
        """The target's pose (its joints' values, ``qpos[target_joints]``) from one depth image:
        the values that put the target pixels' points, back-projected from ``camera``, on the
        surfaces of the target geoms (their union's signed distance, ``Renderer.sdf``) -- a
        Gauss-Newton fit with a Huber loss (``huber`` m), from the guess that moves the target
        geoms' centroid to the points' mean. Model-based perception: the mean of the visible
        pixels alone is off by the faces a pose shows and the arm hides (peg, 12 starts x 6
        steps x 4 random poses: 19-33 mm median). Differentiable in the camera and the images:
        the derivative is the converged fit's (implicit function theorem on its optimality
        condition), not the unrolled iterations'; zeros where no target pixel shows.
        ``points``: target pixels used (a spread subset); ``joints``: the arm's measured angles
        and velocities (14,). The target geoms must be primitives (not meshes).
        ``with_residual``: return ``(pose, rms)``, the fit's weighted RMS signed distance (m; 0
        where no target pixel shows). ``hinge_grid`` K > 1: also start from the hinges turned
        together to K - 1 more angles spread over their period, each alone and with each slide
        moved by +-2.5 cm (a global search; ``bench/pose_views.py`` (in git history) measures what it buys)."""
        from twinrl.render import Geoms, primitives
        from twinrl.render.pointcloud import depth_to_points, huber_residual

        sg = jax.lax.stop_gradient
        idx = np.asarray(self.target_joints)
        model = self.sim.model_with(self.params)
        dt = depth.dtype
        pts, w = depth_to_points(camera, depth, mask)
        n = jnp.sum(w)
        # at most `points` of the target's pixels, spread over it (a fixed pseudo-random order
        # breaks the ties of a hard mask: top_k alone would keep the first rows)
        k = min(int(points), w.shape[0])
        order = jnp.asarray(np.random.default_rng(0).random(w.shape[0]) * 1e-3, dt)
        _, pick = jax.lax.top_k(sg(w) + order, k)
        pts, w = pts[pick], w[pick]
        # sqrt(w / sum w), with a zero (not infinite) slope at the pixels that show no target:
        # a soft mask's gradient reaches them
        shown = w > 0
        sw = jnp.where(shown, jnp.sqrt(jnp.where(shown, w, 1.0) / jnp.maximum(jnp.sum(w), 1e-3)),
                       0.0)
        gid = self.target_geom_ids
        types = np.asarray(self.sim.mj_model.geom_type)[gid]
        size = jnp.asarray(model.geom_size, dt)[gid]
        chain = self._target_chain

        def poses(x):  # the target geoms' (xpos, xmat): their own chain, or all of mjx's
            qpos = self.estimated_state(joints, x)[0]
            if chain.supports:
                return chain(model, qpos)
            g = Geoms.from_mjx(model, self.sim.init(qpos))
            return g.xpos[gid], g.xmat[gid]

        def centroid(x):
            return jnp.mean(poses(x)[0], 0)

        def resid(x, pts, sw):  # the signed distance to the union of the target geoms
            xpos, xmat = poses(x)
            d = jnp.stack([primitives.sdf(int(t), (pts - xpos[i]) @ xmat[i], size[i])
                           for i, t in enumerate(types)], -1)
            return sw * huber_residual(jnp.min(d, -1), huber)

        eye = jnp.eye(idx.size, dtype=dt)

        def damped(A):
            return A + 1e-3 * jnp.diag(jnp.diag(A)) + 1e-9 * eye

        # the fit itself sees the data as constants: its derivative is the converged solution's
        # (below), not that of the unrolled iterations (~1e12 through the needle's soft images)
        data = sg(pts), sg(sw)
        x = jnp.zeros(idx.size, dt)
        Jc = jax.jacfwd(centroid)(x)
        # the mean of the points the fit uses (`n` counts every target pixel, more than those
        # where the image shows over `points` of them)
        mean = jnp.sum(sg(w)[:, None] * data[0], 0) / jnp.maximum(jnp.sum(sg(w)), 1e-3)
        x = jnp.linalg.solve(Jc.T @ Jc + 1e-6 * eye, Jc.T @ (mean - centroid(x)))

        def step(_, x):
            r, J = resid(x, *data), jax.jacfwd(resid)(x, *data)
            A = J.T @ J
            return x - jnp.linalg.solve(damped(A), J.T @ r)

        # restarts: the guess, and the guess moved by +-2.5 and +-5 cm (slides) / +-0.3 and
        # +-0.6 rad (hinges) along each joint; the fit with the smallest residual wins
        hinge = self._target_hinges
        delta = jnp.asarray(np.where(hinge, 0.3, 0.025), dt)
        starts = [x[None]] + [x + m * delta * eye for m in (1, -1, 2, -2)]
        if hinge_grid > 1 and hinge.any():
            h = jnp.asarray(hinge, dt)
            slide = (delta * eye)[~hinge]
            for k in range(1, hinge_grid):
                turned = x + (k * self.target_hinge_period / hinge_grid) * h
                starts += [turned[None], turned + slide, turned - slide]
        starts = jnp.concatenate(starts)
        fits = jax.vmap(lambda x: jax.lax.fori_loop(0, iters, step, x))(starts)
        cost = jax.vmap(lambda x: jnp.sum(jnp.square(resid(x, *data))))(fits)
        x = fits[jnp.argmin(cost)]
        # the derivative of the converged fit in the data, by the implicit function theorem on
        # its optimality condition g(x, data) = J'r = 0: dx = -H^-1 dg, H = dg/dx (the loss's
        # full Hessian: the Gauss-Newton J'J alone was 30-40 % off central differences through
        # soft images, whose fits keep large residuals), added with a zero value
        def normal(x, pts, sw):
            return jax.jacfwd(resid)(x, pts, sw).T @ resid(x, pts, sw)

        H = jax.jacfwd(normal)(x, *data)
        r = resid(x, pts, sw)
        dx = -jnp.linalg.solve(H + 1e-3 * jnp.diag(jnp.abs(jnp.diag(H))) + 1e-9 * eye,
                               normal(x, pts, sw))
        x = x + (dx - sg(dx))
        seen = n > 3.0
        x = jnp.where(seen, self._wrap_target_pose(x), 0.0)
        if not with_residual:
            return x
        # the residual at the optimum moves with the data alone (the envelope theorem)
        c = jnp.sum(jnp.square(r))
        r = jnp.sqrt(jnp.min(cost) + (c - sg(c)) + 1e-12)  # weights sum to 1: an RMS (Huber)
        return x, jnp.where(seen, r, 0.0)

    @functools.cached_property
    def target_geom_ids(self) -> np.ndarray:
        """MuJoCo geom ids of ``target_geoms`` (NumPy: built inside a trace, a cached jax array
        would leak it)."""
        return np.asarray([self.sim.mj_model.geom(g).id for g in self.target_geoms])

    @functools.cached_property
    def _target_chain(self):
        """The target geoms' poses from their own chain's joints (``twinrl.physics.chain``):
        a pose fit traces it in milliseconds where ``mjx.kinematics`` takes seconds."""
        from twinrl.physics.chain import GeomChain

        return GeomChain(self.sim.mj_model, self.target_geom_ids)

    @functools.cached_property
    def _target_columns(self) -> np.ndarray:
        drawn = list(self.renderer.geom_ids)
        return np.asarray([drawn.index(i) for i in self.target_geom_ids])
