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
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import optax

from twinrl._jaxconfig import exact_matmuls, image_compiler_options
from twinrl.real2sim.lm import Linearisation, minimise
from twinrl.render import Camera, Geoms, Renderer, rotvec_to_quat
from twinrl.render.camera import quat_mul, quat_to_mat
from twinrl.render.pointcloud import depth_to_points, sinkhorn_emd

__all__ = ["VisualConfig", "visual_sysid", "fit_camera", "fit_object", "fit_mesh",
           "fit_body_offset", "body_geoms",
           "state_from_obs", "frames_from_dataset", "check_frames", "DEFAULT_OBJECT"]

DEFAULT_OBJECT = {"push": "box", "cartpole_swingup": "cart", "cartpole_balance": "cart",
                  "pendulum_swingup": "bob"}


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


# ---------------------------------------------------------------------- frames
def state_from_obs(env_name: str, obs: np.ndarray) -> np.ndarray:
    """The ``qpos`` of a registered task's (noisy) observation, where the observation determines
    it (box height and tilt of ``push`` are taken at rest on the floor)."""
    return _state_map(env_name)(obs)


def _state_map(env_name: str):
    """``obs -> qpos`` of ``state_from_obs``, the task made once (an arm task's
    ``Env.state_from_obs``)."""
    if env_name.startswith("cartpole"):
        return lambda o: np.array([o[0], np.arctan2(o[2], o[1])], np.float64)
    if env_name == "pendulum_swingup":
        return lambda o: np.array([np.arctan2(o[1], o[0])], np.float64)
    if env_name == "push":
        def push(o):
            yaw = np.arctan2(o[7], o[6])
            return np.array([o[0], o[1], o[4], o[5], 0.05, np.cos(yaw / 2), 0, 0,
                             np.sin(yaw / 2)], np.float64)
        return push
    from twinrl import envs

    env = envs.make(env_name)

    def arm(o):
        try:  # tasks whose observation fixes the pose (the arm tasks: Env.state_from_obs)
            q = env.state_from_obs(np.asarray(o, np.float32))[0]
        except NotImplementedError:
            raise ValueError(f"no observation-to-state map for task {env_name!r}; pass frames "
                             "with 'qpos' instead") from None
        return np.asarray(q, np.float64)
    return arm


def frames_from_dataset(env_name: str, dataset, n: int = 12, seed: int = 0,
                        episodes: Sequence[int] | None = None) -> list[dict]:
    """``n`` frames evenly spread over a dataset recorded with ``twinrl collect --images`` (over
    the rows of ``episodes`` only, when given: e.g. the loop's round-0 episodes), each with the
    ``episode`` it comes from."""
    from twinrl.real.dataset import Dataset, read

    ds = dataset if isinstance(dataset, Dataset) else read(dataset)
    missing = {"rgb", "depth", "segmentation"} - set(ds.images)
    if missing:
        raise ValueError(f"dataset {ds.path} has no {sorted(missing)} images: record it with "
                         "`twinrl collect --images`")
    if ds.meta.get("env") not in (None, env_name):
        raise ValueError(f"dataset {ds.path} was recorded on {ds.meta.get('env')!r}, "
                         f"not {env_name!r}")
    rows = np.arange(len(ds))
    if episodes is not None:
        rows = rows[np.isin(np.asarray(ds.episode_id), np.asarray(list(episodes)))]
    if rows.size == 0:
        raise ValueError(f"dataset {ds.path} is empty" if episodes is None else
                         f"dataset {ds.path} has no rows of episodes {list(episodes)}")
    idx = rows[np.unique(np.linspace(0, rows.size - 1, min(n, rows.size)).round().astype(int))]
    to_qpos = _state_map(env_name)
    # images are rendered after the step: they show next_obs's state
    return [{"rgb": ds.images["rgb"][i], "depth": ds.images["depth"][i],
             "segmentation": ds.images["segmentation"][i],
             "qpos": to_qpos(np.asarray(ds.next_obs[i], np.float64)),
             "episode": int(ds.episode_id[i])} for i in idx]


def check_frames(frames: Sequence[Mapping[str, Any]], nq: int) -> list[dict]:
    """Validate frames (shapes, dtypes, finite values) and return them as NumPy dicts."""
    if not frames:
        raise ValueError("no frames given")
    out, shape = [], None
    for i, f in enumerate(frames):
        for k in ("rgb", "depth", "segmentation", "qpos"):
            if k not in f:
                raise ValueError(f"frame {i} has no {k!r} (keys: {sorted(f)})")
        rgb, depth = np.asarray(f["rgb"]), np.asarray(f["depth"], np.float64)
        seg, qpos = np.asarray(f["segmentation"]), np.asarray(f["qpos"], np.float64)
        H, W = depth.shape if depth.ndim == 2 else (None, None)
        if depth.ndim != 2 or rgb.shape != (H, W, 3) or seg.shape != (H, W):
            raise ValueError(f"frame {i}: need rgb (H, W, 3), depth (H, W), segmentation (H, W);"
                             f" got {rgb.shape}, {depth.shape}, {seg.shape}")
        if shape is not None and (H, W) != shape:
            raise ValueError(f"frame {i} is {H}x{W}; frame 0 is {shape[0]}x{shape[1]}")
        shape = (H, W)
        if rgb.dtype != np.uint8:
            raise ValueError(f"frame {i}: rgb must be uint8, got {rgb.dtype}")
        if not np.all(np.isfinite(depth)) or np.any(depth < 0):
            raise ValueError(f"frame {i}: depth must be finite and >= 0 (NaN or inf found)")
        if qpos.shape != (nq,) or not np.all(np.isfinite(qpos)):
            raise ValueError(f"frame {i}: qpos must be {nq} finite numbers, got {qpos}")
        out.append({"rgb": rgb, "depth": depth, "segmentation": seg.astype(np.int32),
                    "qpos": qpos})
    return out


def _geoms_of(model: mujoco.MjModel, qposes) -> Geoms:
    """Stacked ``Geoms`` (K leading) of the nominal model at each frame's qpos."""
    d = mujoco.MjData(model)
    xs, ms = [], []
    for q in qposes:
        d.qpos[:] = q
        mujoco.mj_kinematics(model, d)
        xs.append(d.geom_xpos.copy())
        ms.append(d.geom_xmat.reshape(-1, 3, 3).copy())
    K = len(xs)
    rep = lambda a: jnp.asarray(np.broadcast_to(a, (K, *a.shape)))  # noqa: E731
    return Geoms(jnp.asarray(np.stack(xs)), jnp.asarray(np.stack(ms)), rep(model.geom_size),
                 rep(model.geom_rgba), rep(np.asarray(model.mesh_vert).reshape(-1, 3)))


# ---------------------------------------------------------------------- the loss
def _soft_iou(w, m):
    inter = jnp.sum(w * m)
    union = jnp.sum(w + m - w * m)
    return inter / jnp.maximum(union, 1e-6)


def _frame_loss(R: Renderer, cfg: VisualConfig, cam: Camera, geoms: Geoms, real: dict, tau,
                focus: int | None, pix_idx):
    """Loss terms of one frame. ``focus``: index (renderer order) of the object whose mask and
    point cloud are compared, or a tuple of them (a body's geoms; None: every geom)."""
    im = R.render(cam, geoms, tau=tau, gamma=cfg.gamma)
    rgb_real = real["rgb"].astype(im.rgb.dtype) / 255.0
    care = real["care"].astype(im.rgb.dtype)  # 0 on pixels of ignored geoms
    terms = {"rgb": jnp.sum(care[..., None] * (im.rgb - rgb_real) ** 2)
             / jnp.maximum(3.0 * jnp.sum(care), 1.0)}
    onehot = (real["segmentation"][..., None] == jnp.asarray(R.geom_ids)).astype(im.rgb.dtype)
    onehot = onehot * care[..., None]
    weights = im.weights * care[..., None]
    if focus is None:
        present = jnp.sum(onehot, (0, 1)) + jnp.sum(weights, (0, 1)) > 0
        ious = jax.vmap(_soft_iou, in_axes=(-1, -1))(weights, onehot)
        terms["iou"] = 1.0 - jnp.sum(ious * present) / jnp.maximum(jnp.sum(present), 1)
        real_w = (real["segmentation"] >= 0).astype(im.rgb.dtype) * care
        sim_w = (1.0 - im.background) * care
    elif isinstance(focus, tuple):  # several geoms (a rigid body's): their IoUs averaged
        idx = np.asarray(focus)
        w_f, o_f = weights[..., idx], onehot[..., idx]
        present = jnp.sum(o_f, (0, 1)) + jnp.sum(w_f, (0, 1)) > 0
        ious = jax.vmap(_soft_iou, in_axes=(-1, -1))(w_f, o_f)
        terms["iou"] = 1.0 - jnp.sum(ious * present) / jnp.maximum(jnp.sum(present), 1)
        real_w, sim_w = jnp.sum(o_f, -1), jnp.sum(w_f, -1)
    else:
        terms["iou"] = 1.0 - _soft_iou(weights[..., focus], onehot[..., focus])
        real_w = onehot[..., focus]
        sim_w = weights[..., focus]
    seen = (real["segmentation"] >= 0).astype(im.rgb.dtype) * care
    terms["depth"] = jnp.sum(seen * jnp.abs(im.depth - real["depth"])) / jnp.maximum(
        jnp.sum(seen), 1.0)
    pts, _ = depth_to_points(cam, real["depth"])
    sd = R.sdf(pts, geoms)  # (H*W, G)
    oh = onehot.reshape(-1, onehot.shape[-1])
    if focus is not None:
        idx = np.asarray(focus if isinstance(focus, tuple) else (focus,))
        oh, sd = oh[:, idx], sd[:, idx]
    # per geom, then averaged over the geoms seen: small objects count as much as the floor
    per = jnp.sum(oh * sd ** 2, 0) / jnp.maximum(jnp.sum(oh, 0), 1.0)
    terms["surface"] = jnp.sum(per) / jnp.maximum(jnp.sum(jnp.sum(oh, 0) > 0), 1)
    if cfg.w_emd > 0:
        pr, wr = depth_to_points(cam, real["depth"], real_w)
        ps, ws = depth_to_points(cam, im.depth, sim_w)
        terms["emd"] = sinkhorn_emd(pr[pix_idx], ps[pix_idx], wr[pix_idx], ws[pix_idx],
                                    epsilon=cfg.emd_epsilon)
    else:
        terms["emd"] = jnp.zeros(())
    total = (cfg.w_rgb * terms["rgb"] + cfg.w_iou * terms["iou"] + cfg.w_depth * terms["depth"]
             + cfg.w_emd * terms["emd"] + cfg.w_surface * terms["surface"])
    return total, terms


def _pixel_subset(frames, n, focus_id, rng):
    """Fixed pixels for the EMD clouds: where the real frames show the object (or any geom),
    grown by a margin so the rendered estimate's points are there too."""
    import scipy.ndimage as ndi

    segs = np.stack([f["segmentation"] for f in frames])
    mask = (segs == focus_id) if focus_id is not None else (segs >= 0)
    mask = ndi.binary_dilation(mask.any(0), iterations=3).ravel()
    cand = np.flatnonzero(mask)
    if cand.size == 0:
        cand = np.arange(mask.size)
    return jnp.asarray(rng.choice(cand, size=min(n, cand.size), replace=cand.size < n))


def _optimise(loss_fn, params0, cfg: VisualConfig, rng: np.random.Generator, perturb):
    """Adam with a coarse-to-fine temperature over restarts; returns (best params, history)."""
    taus = np.geomspace(cfg.tau[0], cfg.tau[1], cfg.steps)
    opt = optax.adam(cfg.lr)

    @functools.partial(jax.jit, compiler_options=image_compiler_options())
    def step(p, s, tau):
        (loss, terms), g = jax.value_and_grad(loss_fn, has_aux=True)(p, tau)
        g = jax.tree_util.tree_map(lambda x: jnp.where(jnp.isfinite(x), x, 0.0), g)
        u, s = opt.update(g, s, p)
        return optax.apply_updates(p, u), s, loss, terms

    final_loss = jax.jit(loss_fn, compiler_options=image_compiler_options())
    best, runs = None, []
    for k in range(cfg.restarts):
        p = params0 if k == 0 else perturb(params0, rng)
        s = opt.init(p)
        for t in range(cfg.steps):
            p, s, loss, terms = step(p, s, taus[t])
        final, terms = final_loss(p, cfg.tau[1])
        final = float(final)
        runs.append({"restart": k, "final_loss": final,
                     **{k2: float(v) for k2, v in terms.items()}})
        if np.isfinite(final) and (best is None or final < best[1]):
            best = (p, final)
    if best is None:
        raise FloatingPointError("every restart of the visual fit diverged (non-finite loss)")
    return best[0], runs


# ---------------------------------------------------------------------- geometric refinement
def _huber_residual(r, c):
    """``twinrl.render.pointcloud.huber_residual``."""
    from twinrl.render.pointcloud import huber_residual

    return huber_residual(r, c)


def _surface_residuals(R: Renderer, cfg: VisualConfig, cam: Camera, geoms: Geoms, real: dict,
                       focus: int | None):
    """Signed distance (m, Huber) of each real depth point, unprojected with ``cam``, to the geom
    the real segmentation assigns it (only the ``focus`` geom's points when given, or those of a
    tuple of geoms); weighted so every geom seen counts as much as any other, whatever its pixel
    count. (H*W,)"""
    pts, _ = depth_to_points(cam, real["depth"])
    sd = R.sdf(pts, geoms)
    oh = (real["segmentation"].reshape(-1, 1) == jnp.asarray(R.geom_ids)).astype(sd.dtype)
    oh = oh * real["care"].reshape(-1, 1).astype(sd.dtype)
    if focus is not None:
        idx = np.asarray(focus if isinstance(focus, tuple) else (focus,))
        oh, sd = oh[:, idx], sd[:, idx]
    n = jnp.sum(oh, 0)
    w = oh / jnp.sqrt(jnp.maximum(n, 1.0) * jnp.maximum(jnp.sum(n > 0), 1))
    return jnp.sum(w * _huber_residual(jnp.where(oh > 0, sd, 0.0), cfg.huber), -1)


def _focus_rays(R: Renderer, cam: Camera, geoms: Geoms, focus: int):
    """Each pixel ray's hit-or-closest-approach depth and signed distance (m) to the ``focus``
    geom. (H*W,) each."""
    o, r = cam.rays()
    _, s_n, dist, _ = R.cast(o, r.reshape(-1, 3), geoms, soft=True)
    return s_n[:, focus], dist[:, focus]


def _free_space_residuals(R: Renderer, cfg: VisualConfig, rays, real: dict, focus: int):
    """How deep (m, Huber) the ray of each pixel the real segmentation does *not* give to the
    ``focus`` geom passes inside that geom in front of the real depth: the silhouette, in metres.
    (H*W,)"""
    s_n, dist = rays
    other = real["segmentation"].reshape(-1) != R.geom_ids[focus]
    pen = jnp.where(other & (s_n < real["depth"].reshape(-1)), jnp.maximum(-dist, 0.0), 0.0)
    n = jnp.sum(real["segmentation"] == R.geom_ids[focus])
    return _huber_residual(pen, cfg.huber) / jnp.sqrt(jnp.maximum(n, 1.0))


def _silhouette_residuals(R: Renderer, cfg: VisualConfig, cam: Camera, rays, real: dict,
                          focus: int):
    """Soft coverage of each unoccluded pixel by the ``focus`` geom (temperature ``tau[1]``
    pixels) minus whether the real segmentation gives it that geom, in metres (times the pixel's
    footprint), times 0.1. Zero-cost placements of an edge span the gap between a labelled and an
    unlabelled pixel centre; this weak term only breaks that tie (towards the gap's middle): with
    full weight it would override the narrower gap that several views' hard constraints leave
    (bench seed 0: 0.7 % -> 3.7 % size error). (H*W,)"""
    s_n, dist = rays
    foot = jnp.maximum(s_n, R.near) * cam.pixel_size()
    cover = jax.nn.sigmoid(-dist / (foot * cfg.tau[1]))
    label = (real["segmentation"].reshape(-1) == R.geom_ids[focus]).astype(cover.dtype)
    # a pixel something else hides (real surface in front of the geom) says nothing of its edge
    seen = (label > 0) | (real["depth"].reshape(-1) >= s_n)
    n = jnp.maximum(jnp.sum(label), 1.0)
    return 0.1 * jnp.where(seen, (cover - label) * jax.lax.stop_gradient(foot), 0.0) / jnp.sqrt(n)


def _lowest_z(geoms: Geoms, gid: int, gtype: int):
    """World height of the lowest point of geom ``gid`` (``Geoms`` of one frame)."""
    R, c, s = geoms.xmat[gid], geoms.xpos[gid, 2], geoms.size[gid]
    rz = R[2]  # the world z component of the geom's local axes
    if gtype == 2:  # sphere
        return c - s[0]
    if gtype == 3:  # capsule
        return c - s[0] - jnp.abs(rz[2]) * s[1]
    if gtype == 5:  # cylinder
        return c - jnp.abs(rz[2]) * s[1] - s[0] * jnp.sqrt(jnp.maximum(1 - rz[2] ** 2, 1e-12))
    if gtype == 4:  # ellipsoid
        return c - jnp.sqrt(jnp.sum((rz * s) ** 2))
    if gtype == 6:  # box
        return c - jnp.sum(jnp.abs(rz) * s)
    raise ValueError(f"keep_support: no lowest point for geom type {gtype}; set "
                     "keep_support=False")


def _levenberg_marquardt(res_fn, params: dict, keys: Sequence[str], iters: int,
                         lam: float = 1e-2, starts: Sequence[dict] = ()):
    """Minimise ``0.5 |res_fn(params)|^2`` over ``params[k]`` for ``k`` in ``keys`` (the others
    held) by Levenberg-Marquardt (``twinrl.real2sim.lm.minimise``) with Marquardt's diagonal
    scaling and a forward-mode Jacobian. ``starts``: further starting values of ``keys`` (dicts
    of them), each refined as well (one compilation for all); the lowest final cost wins.
    Returns the refined params and ``{"cost_before", "cost_after", "iters"}`` of the winner,
    with ``"start"`` (0: ``params``, ``i``: ``starts[i - 1]``) and every start's final cost
    (``"costs"``) when ``starts`` are given."""
    from jax.flatten_util import ravel_pytree

    x0, unravel = ravel_pytree({k: params[k] for k in keys})

    def fun(x):
        return res_fn({**params, **unravel(x)})

    opts = image_compiler_options()  # no MJX here
    f, jac = jax.jit(fun, compiler_options=opts), jax.jit(jax.jacfwd(fun), compiler_options=opts)

    def linearise(point):  # the point carries its residuals: no re-render to linearise
        x, r = point
        J = jac(x)
        A, g = J.T @ J, J.T @ r
        D = jnp.diag(jnp.diag(A) + 1e-9 * jnp.max(jnp.diag(A)) + 1e-30)

        def evaluate(dx):
            r_new = f(x + dx)
            return (x + dx, r_new), float(0.5 * jnp.sum(r_new * r_new))

        return Linearisation(float(0.5 * jnp.sum(r * r)),
                             lambda mu: jnp.linalg.solve(A + mu * D, -g), evaluate)

    results = {}  # start index -> its minimisation
    for i, s in enumerate([None, *starts]):
        x = x0 if s is None else ravel_pytree({k: jnp.asarray(s[k], params[k].dtype)
                                               for k in keys})[0]
        r = f(x)
        if not np.isfinite(float(0.5 * jnp.sum(r * r))):
            if s is None:
                raise FloatingPointError("visual refinement: non-finite residuals at the start")
            continue  # an extra start outside where the residuals are defined: skipped
        results[i] = minimise(linearise, (x, r), damping=lam, iterations=iters, tries=10,
                              rtol_initial=1e-9)
    best = min(results, key=lambda i: results[i].cost)
    res = results[best]
    info = {"cost_before": res.cost0, "cost_after": res.cost, "iters": res.iterations}
    if starts:
        info.update(start=best, costs=[float(results[i].cost) if i in results else None
                                       for i in range(len(starts) + 1)])
    return {**params, **unravel(res.x[0])}, info


# ---------------------------------------------------------------------- camera (a)
def _apply_camera(cam0: Camera, p, local: bool = False) -> Camera:
    """``cam0`` turned by ``p["cam_drot"]`` (in its own frame) and moved by ``p["cam_dpos"]``: in
    the world frame, or with ``local`` in ``cam0``'s own frame (a hand-eye offset)."""
    d = p["cam_dpos"]
    if local:
        d = quat_to_mat(cam0.quat) @ d
    cam = cam0.translated(d)
    return dataclasses.replace(cam, quat=quat_mul(cam0.quat, rotvec_to_quat(p["cam_drot"])))


@exact_matmuls
def fit_camera(model: mujoco.MjModel, frames, cam0: Camera, cfg: VisualConfig = VisualConfig(),
               seed: int = 0, renderer: Renderer | None = None, ignore: Sequence[int] = ()):
    """(a) Camera position and orientation (relative to ``cam0``, in its own frame as
    ``Perturbation.camera_rot_offset``) from frames of a known scene. Returns ``(camera,
    info)``; ``info["pos_offset"]`` / ``["rot_offset"]`` is the fitted offset (the position's in
    the world frame for one camera, in each camera's own frame for a stack).

    ``cam0`` is one camera, the same for every frame, or a stack of them (a leading axis, one per
    frame: ``Camera`` arrays stacked), each frame's *commanded* pose -- a camera on a robot's
    hand seen from several hand poses. One offset, in each commanded camera's own frame (a
    hand-eye offset), is then fitted to all frames and ``camera`` is the stack of fitted
    cameras. From one pose a sideways shift of the camera and a turn of it look alike (the
    scene is far compared with the shift), so only several poses pin the offset itself.

    ``ignore``: ids of geoms whose pose the recorded state does not give well (a tool in a hand
    whose grasp is uncertain): left out of the render, and their real pixels out of every term
    (else the fit turns the camera to bring a misplaced geom's render onto its image)."""
    ignore = sorted({int(g) for g in ignore})
    if ignore and (ignore[0] < 0 or ignore[-1] >= model.ngeom):
        raise ValueError(f"fit_camera: ignore holds geom ids outside 0..{model.ngeom - 1}: "
                         f"{ignore}")
    if renderer is None:
        renderer = Renderer.create(model)
        if ignore:
            renderer = Renderer.create(model, geom_ids=[g for g in renderer.geom_ids
                                                        if g not in ignore])
    elif set(renderer.geom_ids) & set(ignore):
        raise ValueError(f"fit_camera: the renderer draws ignored geoms "
                         f"{sorted(set(renderer.geom_ids) & set(ignore))}")
    R = renderer
    n = len(frames)
    batched = jnp.ndim(cam0.pos) == 2
    if batched and cam0.pos.shape[0] != n:
        raise ValueError(f"fit_camera: {cam0.pos.shape[0]} cameras for {n} frames")
    cams0 = cam0 if batched else jax.tree_util.tree_map(
        lambda a: jnp.broadcast_to(a, (n,) + jnp.shape(a)), cam0)
    geoms = _geoms_of(model, [f["qpos"] for f in frames])
    frames_c, cams0_c, _ = _coarse(frames, cams0, cfg.coarse_size)
    reals_c = _stack_real(frames_c, ignore)
    rng = np.random.default_rng(seed)
    pix = _pixel_subset(frames_c, cfg.emd_points, None, rng)

    def loss_fn(p, tau):
        def one(g, r, c):
            return _frame_loss(R, cfg, _apply_camera(c, p, batched), g, r, tau, None, pix)

        tot, terms = jax.vmap(one)(geoms, reals_c, cams0_c)
        return jnp.mean(tot), jax.tree_util.tree_map(jnp.mean, terms)

    p0 = {"cam_dpos": jnp.zeros(3), "cam_drot": jnp.zeros(3)}

    def perturb(p, rng):
        return {"cam_dpos": p["cam_dpos"] + rng.normal(0, cfg.init_pos_sd, 3),
                "cam_drot": p["cam_drot"] + rng.normal(0, cfg.init_rot_sd, 3)}

    p, runs = _optimise(loss_fn, p0, cfg, rng, perturb)
    refine = None
    if cfg.refine_iters:
        reals = _stack_real(frames, ignore)

        def residuals(p):
            def one(g, r, c):
                return _surface_residuals(R, cfg, _apply_camera(c, p, batched), g, r, None)

            return jax.vmap(one)(geoms, reals, cams0).ravel()

        p, refine = _levenberg_marquardt(residuals, p, ("cam_dpos", "cam_drot"),
                                         cfg.refine_iters)
    cams = jax.vmap(lambda c: _apply_camera(c, p, batched))(cams0)
    camera = cams if batched else jax.tree_util.tree_map(lambda a: a[0], cams)
    return camera, {"runs": runs, "pos_offset": np.asarray(p["cam_dpos"]),
                    "rot_offset": np.asarray(p["cam_drot"]), "refine": refine}


def _stack_real(frames, ignore: Sequence[int] = ()):
    """The frames' images stacked, with ``care``: 0 on the pixels the real segmentation gives to
    a geom in ``ignore``, else 1."""
    segs = np.stack([f["segmentation"] for f in frames])
    return {"rgb": jnp.asarray(np.stack([f["rgb"] for f in frames])),
            "depth": jnp.asarray(np.stack([f["depth"] for f in frames])),
            "segmentation": jnp.asarray(segs),
            "care": jnp.asarray(~np.isin(segs, np.asarray(list(ignore), np.int64)))}


def _crop(frame: Mapping[str, Any], row0: int, col0: int, h: int, w: int, step: int) -> dict:
    """A frame's images cut as ``Camera.window(row0, col0, h, w, step)`` sees them."""
    out = dict(frame)
    for k in ("rgb", "depth", "segmentation"):
        out[k] = np.asarray(frame[k])[row0:row0 + step * h:step, col0:col0 + step * w:step]
    return out


def _coarse(frames, camera: Camera, max_side: int):
    """``(frames, camera, step)`` subsampled by the smallest integer step that brings the longer
    side to ``max_side`` or less (centred; the identity when it already is)."""
    H, W = camera.height, camera.width
    step = -(-max(H, W) // max_side)
    if step == 1:
        return list(frames), camera, 1
    h, w = -(-H // step), -(-W // step)
    r0, c0 = (H - step * (h - 1) - 1) // 2, (W - step * (w - 1) - 1) // 2
    return ([_crop(f, r0, c0, h, w, step) for f in frames], camera.window(r0, c0, h, w, step),
            step)


def _object_windows(frames, camera: Camera, gid: int, margin: int):
    """Per frame, the full-resolution window around the object's real pixels grown by
    ``margin`` pixels, all of one size (the largest) so they batch: ``(frames, cameras)``, the
    cameras stacked (a leading frame axis). The whole image when the object is missing from a
    frame."""
    H, W = camera.height, camera.width
    stack = lambda cams: jax.tree_util.tree_map(lambda *a: jnp.stack(a), *cams)  # noqa: E731
    boxes = []
    for f in frames:
        rows, cols = np.nonzero(np.asarray(f["segmentation"]) == gid)
        if rows.size == 0:
            return list(frames), stack([camera] * len(frames))
        boxes.append((rows.min(), rows.max(), cols.min(), cols.max()))
    b = np.asarray(boxes)
    h = min(H, int((b[:, 1] - b[:, 0]).max()) + 1 + 2 * margin)
    w = min(W, int((b[:, 3] - b[:, 2]).max()) + 1 + 2 * margin)
    out, cams = [], []
    for f, (r_lo, r_hi, c_lo, c_hi) in zip(frames, b):
        r0 = int(np.clip((r_lo + r_hi + 1 - h) // 2, 0, H - h))
        c0 = int(np.clip((c_lo + c_hi + 1 - w) // 2, 0, W - w))
        out.append(_crop(f, r0, c0, h, w, 1))
        cams.append(camera.window(r0, c0, h, w))
    return out, stack(cams)


# ---------------------------------------------------------------------- object (b)
_SIZE_DIMS = {0: 2, 2: 1, 3: 2, 4: 3, 5: 2, 6: 3, 7: 0}


def _apply_object(geoms: Geoms, gid: int, gtype: int, p) -> Geoms:
    rot = quat_to_mat(rotvec_to_quat(p["obj_drot"]))
    nd = _SIZE_DIMS[gtype]
    scale = jnp.exp(jnp.where(jnp.arange(3) < nd, p["obj_logsize"], 0.0))
    size = geoms.size.at[..., gid, :].multiply(scale)
    rgba = geoms.rgba.at[..., gid, :3].set(jax.nn.sigmoid(p["obj_logit_rgb"]))
    return geoms.replace(xpos=geoms.xpos.at[..., gid, :].add(p["obj_dpos"]),
                         xmat=geoms.xmat.at[..., gid, :, :].set(rot @ geoms.xmat[..., gid, :, :]),
                         size=size, rgba=rgba)


def _object_residuals(R: Renderer, cfg: VisualConfig, cameras: Camera, geoms: Geoms, reals,
                      gid: int, gtype: int, focus: int):
    """The object refinement's residuals as a function of the fit's params: per frame (each with
    its camera: ``cameras`` is stacked), the surface, free-space and silhouette terms and
    (``keep_support``) the lowest point's height."""
    def residuals(p):
        g = _apply_object(geoms, gid, gtype, p)

        def frame(g, g0, r, cam):
            rays = _focus_rays(R, cam, g, focus)  # one cast for both ray terms
            res = [_surface_residuals(R, cfg, cam, g, r, focus),
                   _free_space_residuals(R, cfg, rays, r, focus),
                   _silhouette_residuals(R, cfg, cam, rays, r, focus)]
            if cfg.keep_support and gtype in (2, 3, 4, 5, 6):
                res.append(3.0 * (_lowest_z(g, gid, gtype) - _lowest_z(g0, gid, gtype))[None])
            return jnp.concatenate(res)
        return jax.vmap(frame)(g, geoms, reals, cameras).ravel()

    return residuals


@exact_matmuls
def fit_object(model: mujoco.MjModel, frames, camera: Camera, geom: str | int,
               cfg: VisualConfig = VisualConfig(), seed: int = 0,
               renderer: Renderer | None = None):
    """(b) One object's position, orientation, size and colour, with a known camera: offsets of
    its world pose from the frames' states, a log-scale of its size, its RGB (logit). Returns the
    fitted values (``pos_offset``, ``rot_offset``, ``size``, ``rgb``) and per-restart losses."""
    gid = _geom_id(model, geom)
    R = renderer or Renderer.create(model)
    focus = R.index(gid)
    gtype = int(model.geom_type[gid])
    geoms = _geoms_of(model, [f["qpos"] for f in frames])
    frames_c, cam_c, step = _coarse(frames, camera, cfg.coarse_size)
    reals_c = _stack_real(frames_c)
    rng = np.random.default_rng(seed)
    pix = _pixel_subset(frames_c, cfg.emd_points, gid, rng)

    def loss_fn(p, tau):
        g = _apply_object(geoms, gid, gtype, p)
        tot, terms = jax.vmap(lambda g, r: _frame_loss(R, cfg, cam_c, g, r, tau, focus, pix))(
            g, reals_c)
        return jnp.mean(tot), jax.tree_util.tree_map(jnp.mean, terms)

    rgb0 = np.clip(model.geom_rgba[gid, :3], 0.02, 0.98)
    p0 = {"obj_dpos": jnp.zeros(3), "obj_drot": jnp.zeros(3), "obj_logsize": jnp.zeros(3),
          "obj_logit_rgb": jnp.asarray(np.log(rgb0 / (1 - rgb0)))}

    def perturb(p, rng):
        return {**p, "obj_dpos": p["obj_dpos"] + rng.normal(0, cfg.init_pos_sd, 3),
                "obj_logsize": p["obj_logsize"] + rng.normal(0, 0.05, 3)}

    p, runs = _optimise(loss_fn, p0, cfg, rng, perturb)
    refine = None
    if cfg.refine_iters:
        frames_w, cams_w = _object_windows(frames, camera, gid, cfg.roi_margin * step)
        reals = _stack_real(frames_w)
        residuals = _object_residuals(R, cfg, cams_w, geoms, reals, gid, gtype, focus)
        p, refine = _levenberg_marquardt(residuals, p, ("obj_dpos", "obj_drot", "obj_logsize"),
                                         cfg.refine_iters)

        def colour_residuals(p):
            # the object's own pixels (in the real frame and in the refined hard render alike)
            g = _apply_object(geoms, gid, gtype, p)

            def frame(g, r, cam):
                im = R.render(cam, g)
                own = (im.segmentation == R.geom_ids[focus]) & (
                    r["segmentation"] == R.geom_ids[focus])
                d = im.rgb - r["rgb"].astype(im.rgb.dtype) / 255.0
                # Huber at 2/255: the few pixels of a specular highlight that OpenGL interpolates
                # from the vertices (and this renderer computes per pixel) are outliers, not colour
                return jnp.where(own[..., None], _huber_residual(d, 2.0 / 255.0), 0.0).ravel()
            return jax.vmap(frame)(g, reals, cams_w).ravel()

        p, refine["colour"] = _levenberg_marquardt(colour_residuals, p, ("obj_logit_rgb",),
                                                   cfg.refine_iters)
    nd = _SIZE_DIMS[gtype]
    size = np.array(model.geom_size[gid], np.float64)
    size[:nd] *= np.exp(np.asarray(p["obj_logsize"])[:nd])
    return {"geom": model.geom(gid).name, "pos_offset": np.asarray(p["obj_dpos"]),
            "rot_offset": np.asarray(p["obj_drot"]), "size": size,
            "rgb": np.asarray(jax.nn.sigmoid(p["obj_logit_rgb"])), "runs": runs,
            "refine": refine}


# ---------------------------------------------------------------------- a body in its parent (d)
def body_geoms(model: mujoco.MjModel, body: str | int) -> list[int]:
    """Ids of the geoms of ``body`` and of the bodies under it."""
    bid = model.body(body).id
    below = {bid}
    for b in range(bid + 1, model.nbody):  # a body's parent has a smaller id
        if int(model.body_parentid[b]) in below:
            below.add(b)
    return [g for g in range(model.ngeom) if int(model.geom_bodyid[g]) in below]


def _body_frames(model: mujoco.MjModel, qposes, bid: int):
    """Per frame, the body's world position and rotation and its parent's rotation:
    ``(p (K, 3), R (K, 3, 3), R_parent (K, 3, 3))``."""
    d = mujoco.MjData(model)
    out = []
    for q in qposes:
        d.qpos[:] = q
        mujoco.mj_kinematics(model, d)
        out.append((d.xpos[bid].copy(), d.xmat[bid].reshape(3, 3).copy(),
                    d.xmat[model.body_parentid[bid]].reshape(3, 3).copy()))
    return tuple(jnp.asarray(np.stack(a)) for a in zip(*out))


def _apply_body_offset(geoms: Geoms, gids, frames, p) -> Geoms:
    """``geoms`` (K frames) with the geoms ``gids`` of one rigid body moved as the body is when
    its ``body_pos`` grows by ``p["body_dpos"]`` (in its parent's frame) and its ``body_quat``
    is turned by ``p["body_drot"]`` (axis-angle, in its own frame): ``Perturbation``'s
    ``tool_pos_offset`` / ``tool_rot_offset``."""
    pb, Rb, Rp = frames
    Rd = quat_to_mat(rotvec_to_quat(p["body_drot"]))
    M = Rb @ Rd @ jnp.swapaxes(Rb, -1, -2)  # the turn, in world coordinates, about the body
    shift = pb + Rp @ p["body_dpos"]  # (K, 3)
    idx = np.asarray(gids)
    x = geoms.xpos[:, idx] - pb[:, None]
    xpos = shift[:, None] + jnp.einsum("kij,knj->kni", M, x)
    xmat = jnp.einsum("kij,knjl->knil", M, geoms.xmat[:, idx])
    return geoms.replace(xpos=geoms.xpos.at[:, idx].set(xpos),
                         xmat=geoms.xmat.at[:, idx].set(xmat))


@exact_matmuls
def fit_body_offset(model: mujoco.MjModel, frames, camera: Camera, body: str | int = "tool",
                    cfg: VisualConfig = VisualConfig(), seed: int = 0,
                    renderer: Renderer | None = None, prior: tuple[float, float] = (0.01, 1.0),
                    prior_weight: float = 1e-3):
    """(d) Where a rigid body sits in its parent, with a known camera: the offset of its
    ``body_pos`` (m, in the parent's frame) and the turn of its ``body_quat`` (axis-angle, rad,
    in its own frame) that bring the renders of its geoms (and of those of the bodies under it)
    onto the real frames -- a tool's grasp in a robot's hand, which the recorded joints do not
    give. ``camera``: one camera for every frame, or a stack (one per frame; a camera on a robot
    that moves). The loss and the Levenberg-Marquardt refinement are (b)'s, over the body's geoms
    (their IoUs averaged; every real depth point they own pulled onto their surfaces; the rays of
    pixels they do not own kept out of them), plus a weak prior, ``prior_weight`` times the
    offset in units of ``prior`` (m, rad): it holds at zero what the images cannot see (the turn
    of a round peg or a thread about its own axis, which LM's flat direction otherwise sends
    anywhere) and costs a fraction of a millimetre's misfit elsewhere. The refinement starts
    from Adam's result and from the zero offset; the lower final cost is kept (``refine["start"]``
    says which: 0 Adam's, 1 zero). Returns ``{"body", "geoms", "pos_offset", "rot_offset",
    "runs", "refine"}``."""
    try:
        bid = model.body(body).id
    except (KeyError, IndexError):
        raise ValueError(f"fit_body_offset: no body {body!r} in the model; bodies: "
                         f"{[model.body(i).name for i in range(model.nbody)]}") from None
    gids = body_geoms(model, bid)
    R = renderer or Renderer.create(model)
    focus = tuple(R.index(g) for g in gids if g in R.geom_ids)
    if not focus:
        raise ValueError(f"fit_body_offset: body {model.body(bid).name!r} has no geom the "
                         "renderer draws")
    n = len(frames)
    cams = camera if jnp.ndim(camera.pos) == 2 else jax.tree_util.tree_map(
        lambda a: jnp.broadcast_to(a, (n,) + jnp.shape(a)), camera)
    qposes = [f["qpos"] for f in frames]
    geoms = _geoms_of(model, qposes)
    bframes = _body_frames(model, qposes, bid)
    frames_c, cams_c, _ = _coarse(frames, cams, cfg.coarse_size)
    reals_c = _stack_real(frames_c)
    rng = np.random.default_rng(seed)
    seg_ids = [R.geom_ids[i] for i in focus]
    segs = np.stack([f["segmentation"] for f in frames_c])
    mask = np.isin(segs, seg_ids)
    pix = _pixel_subset([{"segmentation": np.where(m, 0, -1)} for m in mask], cfg.emd_points,
                        0, rng)

    def prior_residuals(p):
        return prior_weight * jnp.concatenate([p["body_dpos"] / prior[0],
                                               p["body_drot"] / prior[1]])

    def loss_fn(p, tau):
        g = _apply_body_offset(geoms, gids, bframes, p)
        tot, terms = jax.vmap(
            lambda g, r, c: _frame_loss(R, cfg, c, g, r, tau, focus, pix))(g, reals_c, cams_c)
        terms = jax.tree_util.tree_map(jnp.mean, terms)
        terms["prior"] = jnp.sum(prior_residuals(p) ** 2)
        return jnp.mean(tot) + terms["prior"], terms

    p0 = {"body_dpos": jnp.zeros(3), "body_drot": jnp.zeros(3)}
    sd_pos, sd_rot = 0.25 * cfg.init_pos_sd, cfg.init_rot_sd

    def perturb(p, rng):
        return {"body_dpos": p["body_dpos"] + rng.normal(0, sd_pos, 3),
                "body_drot": p["body_drot"] + rng.normal(0, sd_rot, 3)}

    p, runs = _optimise(loss_fn, p0, cfg, rng, perturb)
    refine = None
    if cfg.refine_iters:
        reals = _stack_real(frames)

        def residuals(p):
            g = _apply_body_offset(geoms, gids, bframes, p)

            def frame(g, r, cam):
                res = [_surface_residuals(R, cfg, cam, g, r, focus)]
                o, d = cam.rays()
                _, s_n, dist, _ = R.cast(o, d.reshape(-1, 3), g, soft=True)
                for f in focus:
                    rays = (s_n[:, f], dist[:, f])
                    res += [_free_space_residuals(R, cfg, rays, r, f),
                            _silhouette_residuals(R, cfg, cam, rays, r, f)]
                return jnp.concatenate(res)
            return jnp.concatenate([jax.vmap(frame)(g, reals, cams).ravel(),
                                    prior_residuals(p)])

        # Refined from Adam's result and from the nominal grasp (zero offset), the lower final
        # cost kept: a small body (a peg: 0-180 pixels of a 64x64 frame) can lead Adam's soft
        # losses into a wrong basin (peg twin 1: the tool point 20 mm off, cost 7.8e-5) where
        # LM from the nominal grasp, 12 mm off, reaches 0.8 mm (cost 4.7e-6).
        p, refine = _levenberg_marquardt(residuals, p, ("body_dpos", "body_drot"),
                                         cfg.refine_iters, starts=[p0])
    return {"body": model.body(bid).name, "geoms": gids,
            "pos_offset": np.asarray(p["body_dpos"]), "rot_offset": np.asarray(p["body_drot"]),
            "runs": runs, "refine": refine}


def _geom_id(model, geom):
    if isinstance(geom, str):
        gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, geom)
        if gid < 0:
            raise ValueError(f"geom {geom!r} is not in the model; geoms: "
                             f"{[model.geom(i).name for i in range(model.ngeom)]}")
        return gid
    if not 0 <= int(geom) < model.ngeom:
        raise ValueError(f"geom id {geom} out of range [0, {model.ngeom})")
    return int(geom)


# ---------------------------------------------------------------------- mesh (c)
def fit_mesh(model: mujoco.MjModel, frames, camera: Camera, geom: str | int,
             cfg: VisualConfig = VisualConfig(), seed: int = 0,
             renderer: Renderer | None = None):
    """(c) The vertices of a mesh geom (its mesh-local ``mesh_vert``), regularised towards the
    initial mesh's edge lengths and a small Laplacian. Returns the fitted vertices (V, 3) of that
    mesh and per-restart losses."""
    gid = _geom_id(model, geom)
    if model.geom_type[gid] != mujoco.mjtGeom.mjGEOM_MESH:
        raise ValueError(f"geom {geom!r} is not a mesh")
    R = renderer or Renderer.create(model)
    focus = R.index(gid)
    mid = int(model.geom_dataid[gid])
    va, vn = int(model.mesh_vertadr[mid]), int(model.mesh_vertnum[mid])
    fa, fn = int(model.mesh_faceadr[mid]), int(model.mesh_facenum[mid])
    faces = np.asarray(model.mesh_face[fa:fa + fn])
    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]],
                                              faces[:, [2, 0]]]), 1), axis=0)
    geoms = _geoms_of(model, [f["qpos"] for f in frames])
    v0 = jnp.asarray(model.mesh_vert[va:va + vn], geoms.mesh_vert.dtype)
    len0 = jnp.linalg.norm(v0[edges[:, 0]] - v0[edges[:, 1]], axis=-1)
    deg = np.bincount(edges.ravel(), minlength=vn)
    frames_c, cam_c, _ = _coarse(frames, camera, cfg.coarse_size)
    reals = _stack_real(frames_c)
    rng = np.random.default_rng(seed)
    pix = _pixel_subset(frames_c, cfg.emd_points, gid, rng)

    def regulariser(v):
        ln = jnp.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=-1)
        nb = jnp.zeros_like(v).at[edges[:, 0]].add(v[edges[:, 1]]).at[edges[:, 1]].add(
            v[edges[:, 0]])
        lap = v - nb / deg[:, None]
        lap0 = v0 - (jnp.zeros_like(v0).at[edges[:, 0]].add(v0[edges[:, 1]]).at[
            edges[:, 1]].add(v0[edges[:, 0]])) / deg[:, None]
        return jnp.mean(((ln - len0) / len0) ** 2) + jnp.mean(jnp.sum((lap - lap0) ** 2, -1)) / (
            jnp.mean(len0) ** 2)

    def loss_fn(p, tau):
        v = v0 + p["dvert"]
        g = geoms.replace(mesh_vert=geoms.mesh_vert.at[..., va:va + vn, :].set(v))
        tot, terms = jax.vmap(lambda g, r: _frame_loss(R, cfg, cam_c, g, r, tau, focus, pix))(
            g, reals)
        reg = regulariser(v)
        terms = jax.tree_util.tree_map(jnp.mean, terms)
        terms["mesh_reg"] = reg
        return jnp.mean(tot) + cfg.mesh_smooth * reg, terms

    p0 = {"dvert": jnp.zeros_like(v0)}

    def perturb(p, rng):
        return {"dvert": p["dvert"] + rng.normal(0, 0.002, p["dvert"].shape)}

    p, runs = _optimise(loss_fn, p0, cfg, rng, perturb)
    return {"geom": model.geom(gid).name, "vertices": np.asarray(v0 + p["dvert"]), "runs": runs}


# ---------------------------------------------------------------------- the command's function
def visual_sysid(env_name: str, frames_or_dataset, out_dir: str | os.PathLike, seed: int = 0,
                 *, fit: Sequence[str] = ("camera", "object"), object_geom: str | None = None,
                 camera: str | None = None, n_frames: int = 12,
                 config: VisualConfig | None = None) -> dict:
    """Fit the camera, then an object, of task ``env_name`` to real frames; write
    ``out_dir/summary.json`` and ``out_dir/visual_<stage>.png`` (real | rendered before |
    rendered after, per frame) and return the summary.

    Args:
      env_name: registered task (``twinrl envs``).
      frames_or_dataset: a dataset directory or ``Dataset`` (``twinrl collect --images``), or a
        list of frame dicts (``rgb``, ``depth``, ``segmentation``, ``qpos``).
      out_dir: where the summary and PNGs go (created).
      seed: restarts and pixel sampling.
      fit: stages, in order, from ``"camera"`` (a) and ``"object"`` (b); the object is fitted
        with the camera found by (a) when both run.
      object_geom: the object's geom name (default: the task's, ``DEFAULT_OBJECT``).
      camera: camera name (default: the task's first).
      n_frames: frames taken from a dataset.
      config: ``VisualConfig``.
    """
    from twinrl import report
    from twinrl.envs import make

    cfg = config or VisualConfig()
    unknown = set(fit) - {"camera", "object"}
    if unknown or not fit:
        raise ValueError(f"fit must name stages from ('camera', 'object'), got {fit!r}")
    env = make(env_name)
    model = env.sim.mj_model
    cam_name = camera or env.cameras[0]
    if isinstance(frames_or_dataset, (str, os.PathLike)) or hasattr(frames_or_dataset, "images"):
        frames = frames_from_dataset(env_name, frames_or_dataset, n_frames, seed)
    else:
        frames = list(frames_or_dataset)
    frames = check_frames(frames, model.nq)
    H, W = frames[0]["depth"].shape
    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    cam0 = Camera.from_mujoco(model, d, cam_name, W, H)
    R = Renderer.create(model)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {"env": env_name, "seed": seed, "frames": len(frames),
                               "image_size": [W, H], "camera_name": cam_name,
                               "config": dataclasses.asdict(cfg)}
    cam = cam0
    geoms = _geoms_of(model, [f["qpos"] for f in frames])
    t0 = time.perf_counter()
    if "camera" in fit:
        cam, info = fit_camera(model, frames, cam0, cfg, seed, R)
        _save_panels(out / "visual_camera.png", R, frames, (cam0, geoms), (cam, geoms))
        summary["camera"] = {"pos": np.asarray(cam.pos), "quat": np.asarray(cam.quat),
                             "pos_offset_world": info["pos_offset"],
                             "rot_offset_camera": info["rot_offset"], "runs": info["runs"],
                             "refine": info["refine"]}
    if "object" in fit:
        name = object_geom or DEFAULT_OBJECT.get(env_name)
        if name is None:
            raise ValueError(f"no default object for task {env_name!r}: pass object_geom")
        res = fit_object(model, frames, cam, name, cfg, seed, R)
        gid = _geom_id(model, name)
        after = _apply_object(geoms, gid, int(model.geom_type[gid]), {
            "obj_dpos": jnp.asarray(res["pos_offset"]), "obj_drot": jnp.asarray(res["rot_offset"]),
            "obj_logsize": jnp.log(jnp.asarray(res["size"] / np.where(
                model.geom_size[gid] > 0, model.geom_size[gid], 1.0))),
            "obj_logit_rgb": jnp.asarray(np.log(res["rgb"] / (1 - res["rgb"])))})
        _save_panels(out / "visual_object.png", R, frames, (cam, geoms), (cam, after))
        summary["object"] = res
    summary["seconds"] = time.perf_counter() - t0
    rows = []
    if "camera" in summary:
        c = summary["camera"]
        rows.append(["camera", f"dpos {np.round(c['pos_offset_world'] * 1e3, 1)} mm",
                     f"drot {np.round(np.rad2deg(c['rot_offset_camera']), 2)} deg",
                     min(r["final_loss"] for r in c["runs"])])
    if "object" in summary:
        o = summary["object"]
        rows.append([f"object {o['geom']}", f"dpos {np.round(o['pos_offset'] * 1e3, 1)} mm",
                     f"size {np.round(o['size'], 4)} rgb {np.round(o['rgb'] * 255, 1)}",
                     min(r["final_loss"] for r in o["runs"])])
    report.print_table(f"visual real2sim: {env_name}", ["stage", "position", "other", "loss"],
                       rows)
    report.write_json(out / "summary.json", summary)
    return report.to_jsonable(summary)


def _save_panels(path: Path, R: Renderer, frames, before, after, max_frames: int = 4) -> None:
    """Rows of real | rendered before | rendered after (hard images, RGB)."""
    import imageio.v2 as imageio

    rows = []
    for k, f in enumerate(frames[:max_frames]):
        imgs = [f["rgb"]]
        for cam, geoms in (before, after):
            g = jax.tree_util.tree_map(lambda x: x[k], geoms)
            rgb = np.asarray(R.render(cam, g).rgb)
            imgs.append((np.clip(rgb, 0, 1) * 255).round().astype(np.uint8))
        sep = np.full((f["rgb"].shape[0], 2, 3), 255, np.uint8)
        rows.append(np.concatenate([imgs[0], sep, imgs[1], sep, imgs[2]], 1))
    imageio.imwrite(path, np.concatenate(rows, 0))
