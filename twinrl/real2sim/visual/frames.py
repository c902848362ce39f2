"""Frames of a visual fit: read from a recorded dataset (``frames_from_dataset``), checked
(``check_frames``), and prepared for the fits -- stacked into arrays, cut to a window,
subsampled to a coarse image, and the nominal scene's geoms posed at each frame's state.

A frame is a dict with ``rgb`` (H, W, 3) uint8, ``depth`` (H, W) metres, ``segmentation``
(H, W) geom ids and ``qpos``."""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from twinrl.render import Camera, Geoms


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


def stack_frames(frames, ignore: Sequence[int] = ()):
    """The frames' images stacked, with ``care``: 0 on the pixels the real segmentation gives to
    a geom in ``ignore``, else 1."""
    segs = np.stack([f["segmentation"] for f in frames])
    return {"rgb": jnp.asarray(np.stack([f["rgb"] for f in frames])),
            "depth": jnp.asarray(np.stack([f["depth"] for f in frames])),
            "segmentation": jnp.asarray(segs),
            "care": jnp.asarray(~np.isin(segs, np.asarray(list(ignore), np.int64)))}


def crop_frame(frame: Mapping[str, Any], row0: int, col0: int, h: int, w: int,
               step: int) -> dict:
    """A frame's images cut as ``Camera.window(row0, col0, h, w, step)`` sees them."""
    out = dict(frame)
    for k in ("rgb", "depth", "segmentation"):
        out[k] = np.asarray(frame[k])[row0:row0 + step * h:step, col0:col0 + step * w:step]
    return out


def coarse_frames(frames, camera: Camera, max_side: int):
    """``(frames, camera, step)`` subsampled by the smallest integer step that brings the longer
    side to ``max_side`` or less (centred; the identity when it already is)."""
    H, W = camera.height, camera.width
    step = -(-max(H, W) // max_side)
    if step == 1:
        return list(frames), camera, 1
    h, w = -(-H // step), -(-W // step)
    r0, c0 = (H - step * (h - 1) - 1) // 2, (W - step * (w - 1) - 1) // 2
    return ([crop_frame(f, r0, c0, h, w, step) for f in frames], camera.window(r0, c0, h, w, step),
            step)


def object_windows(frames, camera: Camera, gid: int, margin: int):
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
        out.append(crop_frame(f, r0, c0, h, w, 1))
        cams.append(camera.window(r0, c0, h, w))
    return out, stack(cams)


def nominal_geoms(model: mujoco.MjModel, qposes) -> Geoms:
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
