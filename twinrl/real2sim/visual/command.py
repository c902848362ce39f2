"""``visual_sysid``: the camera, then an object, of a registered task fitted to real frames, with
a summary table printed, ``summary.json`` and before/after panels written (what ``twinrl
sysid --visual`` runs)."""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from twinrl.real2sim.visual.config import VisualConfig
from twinrl.real2sim.visual.fits import apply_object, fit_camera, fit_object, geom_id
from twinrl.real2sim.visual.frames import check_frames, frames_from_dataset, nominal_geoms
from twinrl.render import Camera, Renderer

DEFAULT_OBJECT = {"push": "box", "cartpole_swingup": "cart", "cartpole_balance": "cart",
                  "pendulum_swingup": "bob"}
"""The object ``visual_sysid`` fits by default, per task."""


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
    geoms = nominal_geoms(model, [f["qpos"] for f in frames])
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
        gid = geom_id(model, name)
        after = apply_object(geoms, gid, int(model.geom_type[gid]), {
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
