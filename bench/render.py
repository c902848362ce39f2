"""Benchmark of the differentiable renderer (twinrl.render) and of visual Real2Sim.

1. Speed: frames/s at 64x64 and 128x128, batch 1 and 16 (vmap over cameras), forward only and
   forward + gradient (of an image loss w.r.t. the camera and the geoms), soft image (tau > 0).
2. Agreement with OpenGL (``mujoco.Renderer``) on every bundled scene: mean |depth difference|,
   segmentation agreement, RGB PSNR.
3. Visual Real2Sim (``--visual``): over seeds, hidden camera offsets of 3-4 cm and 5-6 degrees
   (``Perturbation`` constructed directly) and a hidden object pose/size/colour change on
   ``push``; (a) camera fitted with the scene known, (b) the box fitted with the camera known.
   Frames are ``--size`` square (default 256: a real RGB-D camera's resolution order, where a
   pixel is 3.75 mm at the box), ``--frames`` of them (default 5); the Adam stage sees every
   4th pixel (``--coarse`` 64), the refinement every pixel.

Prints tables and writes ``bench/results/render.json``.

    .venv/bin/python bench/render.py [--visual] [--seeds 0 1 2 3 4] [--size 256] [--frames 5]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from twinrl import report  # noqa: E402
from twinrl.physics import load_mjcf  # noqa: E402
from twinrl.physics.scenes import SCENES  # noqa: E402
from twinrl.render import Camera, Geoms, Renderer, quat_to_mat  # noqa: E402

CAMS = {"cartpole": ("front", [0.3, 0.5]), "pendulum": ("front", [0.7]),
        "push": ("top", None), "peg_in_hole": ("front", [0.01, -0.02])}


def _time(f, *args, reps=10):
    jax.block_until_ready(f(*args))
    t = time.perf_counter()
    for _ in range(reps):
        jax.block_until_ready(f(*args))
    return (time.perf_counter() - t) / reps


def speed(sizes=(64, 128), batches=(1, 16)):
    m = load_mjcf("push")
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    R = Renderer.create(m)
    g = Geoms.from_mujoco(m, d)
    rows = []
    for S in sizes:
        cam = Camera.from_mujoco(m, d, "top", S, S)
        target = R.render(cam, g, tau=0.5).rgb
        for B in batches:
            cams = jax.tree_util.tree_map(
                lambda x: jnp.stack([x] * B) + 0.001 * jnp.arange(B).reshape(
                    (B,) + (1,) * x.ndim), cam)

            def loss(c, g):
                return jnp.mean((R.render(c, g, tau=0.5).rgb - target) ** 2)

            fwd = jax.jit(jax.vmap(lambda c: R.render(c, g, tau=0.5).rgb))
            grad = jax.jit(jax.vmap(jax.grad(loss, argnums=(0, 1)), in_axes=(0, None)))
            for name, f in (("forward", fwd), ("forward+grad", grad)):
                args = (cams,) if name == "forward" else (cams, g)
                dt = _time(f, *args, reps=3 if S > 64 or B > 1 else 10)
                rows.append({"size": S, "batch": B, "mode": name, "frames_per_s": B / dt})
    return rows


def agreement(S=64):
    from twinrl.render.opengl import CameraRenderer

    rows = []
    for scene in SCENES:
        cam_name, qpos = CAMS[scene]
        m = load_mjcf(scene)
        d = mujoco.MjData(m)
        if qpos is not None:
            d.qpos[:] = qpos
        mujoco.mj_forward(m, d)
        gl_r = CameraRenderer(m, S, S)
        gl = gl_r.images(d, cam_name)
        gl_r.close()
        im = Renderer.create(m).render(Camera.from_mujoco(m, d, cam_name, S, S),
                                       Geoms.from_mujoco(m, d))
        seg = np.asarray(im.segmentation)
        dd = np.abs(np.asarray(im.depth) - gl["depth"])
        mse = np.mean((np.clip(np.asarray(im.rgb), 0, 1) * 255 - gl["rgb"]) ** 2)
        rows.append({"scene": scene, "depth_mean_abs_m": float(dd.mean()),
                     "depth_mean_abs_on_geoms_m": float(dd[seg >= 0].mean()),
                     # a pixel OpenGL's tessellated silhouette gives to the background (far plane,
                     # ~200 m away) dominates the plain mean; this is the mean where both agree
                     "depth_mean_abs_where_seg_agrees_m": float(
                         dd[seg == gl["segmentation"]].mean()),
                     "segmentation_agreement": float(np.mean(seg == gl["segmentation"])),
                     "rgb_psnr_db": float(10 * np.log10(255.0 ** 2 / mse))})
    return rows


# ---------------------------------------------------------------------- visual real2sim
def _rot_err_deg(q1, q2):
    A, B = np.asarray(quat_to_mat(jnp.asarray(q1))), np.asarray(quat_to_mat(jnp.asarray(q2)))
    return float(np.rad2deg(np.arccos(np.clip((np.trace(A.T @ B) - 1) / 2, -1, 1))))


def _real_frames(m_real, S, qposes):
    from twinrl.render.opengl import render_states

    frames = render_states(m_real, "top", qposes, S, S)
    d = mujoco.MjData(m_real)
    d.qpos[:] = qposes[-1]
    mujoco.mj_forward(m_real, d)
    cam = Camera.from_mujoco(m_real, d, "top", S, S)
    return frames, cam


def visual(seeds, S, cfg):
    from twinrl.real.perturbation import Perturbation
    from twinrl.real2sim import visual as V

    m = load_mjcf("push")
    d0 = mujoco.MjData(m)
    mujoco.mj_forward(m, d0)
    cam0 = Camera.from_mujoco(m, d0, "top", S, S)
    box = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "box")
    rows = []
    for seed in seeds:
        rng = np.random.default_rng(1000 + seed)
        extra = np.random.default_rng(2000 + seed)
        unit = lambda v: v / np.linalg.norm(v)  # noqa: E731
        pos_off = unit(rng.normal(size=3)) * rng.uniform(0.03, 0.04)
        rot_off = unit(rng.normal(size=3)) * np.deg2rad(rng.uniform(5.0, 6.0))
        pert = Perturbation(camera_pos_offset=tuple(pos_off), camera_rot_offset=tuple(rot_off))
        qposes = []
        for k in range(cfg["frames"]):
            # frames past the third come from their own stream: the hidden values (drawn next)
            # stay the same whatever the number of frames
            r = rng if k < 3 else extra
            q = m.qpos0.copy()
            q[0:2] = r.uniform(-0.12, 0.12, 2)
            q[2:4] = np.array([0.15, 0.0]) + r.uniform(-0.05, 0.05, 2)
            qposes.append(q)
        # (a) camera, scene known
        m_real = load_mjcf("push")
        pert.apply(m_real)
        frames, true_cam = _real_frames(m_real, S, qposes)
        t = time.perf_counter()
        cam, info = V.fit_camera(m, V.check_frames(frames, m.nq), cam0, cfg["camera"], seed)
        t_cam = time.perf_counter() - t
        # (b) object, camera known: the real box is moved, resized and recoloured (hidden)
        m_obj = load_mjcf("push")
        pert.apply(m_obj)
        scale = np.exp(rng.uniform(-0.12, 0.12, 3))
        m_obj.geom_size[box] *= scale
        rgb_true = np.clip(m.geom_rgba[box, :3] + rng.uniform(-0.12, 0.12, 3), 0.05, 0.95)
        m_obj.geom_rgba[box, :3] = rgb_true
        dpos = np.r_[rng.uniform(-0.015, 0.015, 2), 0.0]
        dz = m_obj.geom_size[box, 2] - m.geom_size[box, 2]  # the box still rests on the floor
        qposes_b = [q.copy() for q in qposes]
        for q in qposes_b:
            q[2:5] += dpos + np.array([0, 0, dz])
        frames_b, _ = _real_frames(m_obj, S, qposes_b)
        frames_b = [{**f, "qpos": q} for f, q in zip(frames_b, qposes)]  # the nominal guess
        t = time.perf_counter()
        res = V.fit_object(m, V.check_frames(frames_b, m.nq), true_cam, "box", cfg["object"],
                           seed)
        t_obj = time.perf_counter() - t
        true_off = dpos + np.array([0, 0, dz])
        rows.append({
            "seed": seed,
            "hidden_cam_offset_mm": float(np.linalg.norm(pos_off) * 1e3),
            "hidden_cam_rot_deg": float(np.rad2deg(np.linalg.norm(rot_off))),
            "cam_pos_err_mm_before": float(np.linalg.norm(cam0.pos - true_cam.pos) * 1e3),
            "cam_pos_err_mm": float(np.linalg.norm(np.asarray(cam.pos - true_cam.pos)) * 1e3),
            "cam_rot_err_deg_before": _rot_err_deg(cam0.quat, true_cam.quat),
            "cam_rot_err_deg": _rot_err_deg(cam.quat, true_cam.quat),
            "obj_pos_err_mm_before": float(np.linalg.norm(true_off) * 1e3),
            "obj_pos_err_mm": float(np.linalg.norm(res["pos_offset"] - true_off) * 1e3),
            "size_err_pct_before": float(np.max(np.abs(m.geom_size[box] / m_obj.geom_size[box]
                                                       - 1)) * 100),
            "size_err_pct": float(np.max(np.abs(res["size"] / m_obj.geom_size[box] - 1)) * 100),
            "colour_err_255_before": float(np.max(np.abs(m.geom_rgba[box, :3] - rgb_true)) * 255),
            "colour_err_255": float(np.max(np.abs(res["rgb"] - rgb_true)) * 255),
            "seconds_camera": t_cam, "seconds_object": t_obj,
        })
        print(rows[-1], flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--visual", action="store_true", help="also run the visual Real2Sim fits")
    ap.add_argument("--no-speed", action="store_true")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--size", type=int, default=256, help="image size of the visual fits' frames")
    ap.add_argument("--frames", type=int, default=5, help="frames per visual fit")
    ap.add_argument("--coarse", type=int, default=64,
                    help="image size the Adam stage sees (VisualConfig.coarse_size)")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--refine-iters", type=int, default=30,
                    help="Levenberg-Marquardt iterations after Adam (0: Adam only)")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "render.json"))
    args = ap.parse_args(argv)
    out = {"cpu_count": os.cpu_count(), "jax": jax.__version__, "devices": str(jax.devices())}
    prev = {}
    if Path(args.out).exists():
        import json

        prev = json.loads(Path(args.out).read_text())
    if not args.no_speed:
        out["speed"] = speed()
        report.print_table("renderer speed (push scene, soft image)",
                           ["size", "batch", "mode", "frames/s"],
                           [[r["size"], r["batch"], r["mode"], r["frames_per_s"]]
                            for r in out["speed"]])
    elif "speed" in prev:
        out["speed"] = prev["speed"]
    out["agreement"] = agreement()
    report.print_table("hard image vs OpenGL (mujoco.Renderer), 64x64",
                       ["scene", "depth mean|d| (m)", "where seg agrees (m)", "seg agree",
                        "RGB PSNR"],
                       [[r["scene"], r["depth_mean_abs_m"], r["depth_mean_abs_where_seg_agrees_m"],
                         r["segmentation_agreement"], r["rgb_psnr_db"]]
                        for r in out["agreement"]])
    if args.visual:
        from twinrl.real2sim.visual import VisualConfig

        vc = VisualConfig(steps=args.steps, restarts=1, refine_iters=args.refine_iters,
                          coarse_size=args.coarse)
        cfg = {"frames": args.frames, "camera": vc, "object": vc}
        rows = visual(args.seeds, args.size, cfg)
        out["visual"] = {"size": args.size, "frames": args.frames, "coarse": args.coarse,
                         "steps": args.steps, "refine_iters": args.refine_iters, "rows": rows}
        keys = ["cam_pos_err_mm", "cam_rot_err_deg", "obj_pos_err_mm", "size_err_pct",
                "colour_err_255"]
        report.print_table(f"visual real2sim on push, {args.frames} frames, "
                           f"{args.size}x{args.size} (before -> after)",
                           ["seed", "hidden cam", *keys],
                           [[r["seed"], f"{r['hidden_cam_offset_mm']:.0f} mm "
                             f"{r['hidden_cam_rot_deg']:.1f} deg",
                             *[f"{r[k + '_before']:.3g} -> {r[k]:.3g}" for k in keys]]
                            for r in rows])
    elif "visual" in prev:
        out["visual"] = prev["visual"]
    report.write_json(args.out, out)


if __name__ == "__main__":
    main()
