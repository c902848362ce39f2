"""Hand-eye calibration of the arm tasks' camera mount, as the SAM-RL loop does it, against the
hidden truth: with the tool in the fit and left out, from one mount pose or several.

Per task and twin seed: records ``--episodes`` round-0 episodes of the loop's exciting motions
on the real twin the loop would face (``twinrl run --seed S``: the seed's default salt; the
dataset is kept in ``OUT/TASK-S-P/`` and reused), seen from ``P`` mount poses
(``CameraMount.calibration_poses``; ``--poses 1 5``), then fits the mount's offset
(``twinrl.real2sim.handeye.calibrate_mount``, the loop's settings: ``--frames`` frames,
``ArmLoopConfig.calibration_steps`` Adam steps or ``--steps``, one start) with the tool in the
fit and without it (``--variants``), and scores each against the twin's hidden offset
(``twinrl.eval.hand_eye_errors``: evaluation only). With ``--grasp`` each calibration is
followed by the loop's identification of the tool's grasp in the hand with that camera
(``handeye.fit_grasp``), scored by ``twinrl.eval.grasp_errors`` (the tool centre point's error,
mm, against the nominal grasp's); "LM kept" says which refinement won (from Adam's result or
from the zero offset: ``visual.fit_body_offset``).

Prints a table and writes ``OUT/hand_eye.json``. About 1-3 minutes per fit on 2 cores at the
loop's 40 steps.

    python bench/hand_eye.py --tasks needle_threading --seeds 0 --out B
    python bench/hand_eye.py --tasks peg_insertion spatula_flipping --seeds 0 1 2 --out B
    python bench/hand_eye.py --tasks needle_threading --seeds 0 --poses 1 5 --out B
    python bench/hand_eye.py --tasks needle_threading --seeds 0 1 2 --variants tool-out \
        --grasp --out B
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

import twinrl  # noqa: F401  (compilation cache)
from twinrl import envs
from twinrl import eval as evaluation
from twinrl.report import print_table
from benchio import write_result  # noqa: E402  (bench/benchio.py: the results' common meta)

TASKS = ("peg_insertion", "spatula_flipping", "needle_threading")
VARIANTS = ("tool-out", "tool-in")


def record(task: str, seed: int, poses: np.ndarray, episodes: int, out: Path):
    """Round 0 of the loop (its excitation, reset seeds and images) on the twin ``twinrl run
    --seed seed`` faces, episode ``e`` seen from ``poses[e % len(poses)]``; kept in ``out``."""
    from twinrl.loop.arm import record_round0
    from twinrl.real.dataset import DatasetWriter, read
    from twinrl.real.remote import TwinClient

    env = envs.make(task)
    if (out / "dataset" / "meta.json").exists():
        data = read(out / "dataset")
        if len(set(np.asarray(data.episode_id).tolist())) >= episodes:
            return data
    n = int(env.config.image_size)
    twin = TwinClient(task, seed=seed, secret=out / "eval" / "twin.json", width=n, height=n)
    try:
        obs0, _ = twin.reset(seed=seed)
        shapes = {"rgb": (n, n, 3), "depth": (n, n), "segmentation": (n, n)}
        with DatasetWriter(out / "dataset", env=task, obs_shape=obs0.shape,
                           action_shape=twin.action_space.shape, obs_dtype=np.float32,
                           action_dtype=np.float32, image_shapes=shapes) as w:
            at = poses[np.arange(episodes) % len(poses)]
            record_round0(twin, w, env, seed, at, range(w.episode_id, episodes))
    finally:
        twin.close()
    return read(out / "dataset")


def run(args) -> list[dict]:
    from twinrl.real2sim.handeye import calibrate_mount, fit_grasp
    from twinrl.real2sim import visual

    rows = []
    for task in args.tasks:
        env = envs.make(task)
        for seed in args.seeds:
            for n_poses in args.poses:
                poses = env.mount.calibration_poses(n_poses)
                d = args.out / f"{task}-{seed}-{n_poses}"
                data = record(task, seed, poses, args.episodes, d)
                frames = visual.frames_from_dataset(task, data, args.frames,
                                                    episodes=range(args.episodes))
                at = poses[[f["episode"] % len(poses) for f in frames]]
                frames = visual.check_frames(frames, env.sim.mj_model.nq)
                for variant, steps in ((v, n) for v in args.variants for n in args.steps):
                    cfg = visual.VisualConfig(steps=steps, restarts=1)
                    t0 = time.perf_counter()
                    mount, _ = calibrate_mount(env, frames, at, cfg, seed + 1,
                                               ignore_tool=variant == "tool-out")
                    he_seconds = time.perf_counter() - t0
                    err = evaluation.hand_eye_errors(task, seed, mount,
                                                     secret=d / "eval" / "twin.json")
                    if args.grasp:
                        t1 = time.perf_counter()
                        g = fit_grasp(env, mount, frames, at, cfg, seed + 1)
                        err.update(evaluation.grasp_errors(
                            task, seed, g["pos_offset"], g["rot_offset"],
                            secret=d / "eval" / "twin.json"),
                                   grasp_seconds=time.perf_counter() - t1,
                                   grasp_refine=g["refine"])
                    rows.append({"task": task, "seed": seed, "poses": n_poses,
                                 "variant": variant, "frames": len(frames), "steps": steps,
                                 "seconds": time.perf_counter() - t0,
                                 "hand_eye_seconds": he_seconds, **err})
                    print(f"  {task} seed {seed}, {n_poses} pose(s), {variant}, {steps} steps: "
                          f"{err['hand_eye_pos_err_mm']:.2f} mm / "
                          f"{err['hand_eye_rot_err_deg']:.3f} deg" + (
                              f"; grasp: tool point {err['grasp_tcp_err_mm']:.2f} mm "
                              f"(nominal {err['nominal_tcp_err_mm']:.2f})" if args.grasp
                              else ""), flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", nargs="+", choices=TASKS, default=["needle_threading"])
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--poses", nargs="+", type=int, default=[1],
                   help="mount poses round 0 is spread over (one value per case)")
    p.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    p.add_argument("--grasp", action="store_true",
                   help="also identify the tool's grasp with each calibrated camera")
    p.add_argument("--episodes", type=int, default=5)
    p.add_argument("--frames", type=int, default=None,
                   help="round-0 frames each fit uses (the loop's calibration_frames)")
    p.add_argument("--steps", nargs="+", type=int, default=None,
                   help="Adam steps of each fit (the loop's calibration_steps; one value per "
                        "case)")
    p.add_argument("--out", type=Path, default=Path("bench/results"))
    args = p.parse_args(argv)
    from twinrl.loop.arm_config import ArmLoopConfig

    if args.steps is None:
        args.steps = [ArmLoopConfig.calibration_steps]
    if args.frames is None:
        args.frames = ArmLoopConfig.calibration_frames
    if min(args.poses) < 1 or args.episodes < 1 or args.frames < 1 or min(args.steps) < 1:
        p.error("--poses, --episodes, --frames and --steps must be >= 1")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = run(args)
    write_result(args.out / "hand_eye.json", {"rows": rows}, args)
    print_table("hand-eye calibration against the hidden offset",
                ["task", "seed", "poses", "tool", "frames", "steps", "position (mm)",
                 "rotation (deg)", "uncalibrated", "seconds"],
                [[r["task"], r["seed"], r["poses"], r["variant"].removeprefix("tool-"),
                  r["frames"], r["steps"], f"{r['hand_eye_pos_err_mm']:.2f}",
                  f"{r['hand_eye_rot_err_deg']:.3f}",
                  f"{r['uncalibrated_pos_err_mm']:.1f} mm / "
                  f"{r['uncalibrated_rot_err_deg']:.2f} deg",
                  f"{r.get('hand_eye_seconds', r['seconds']):.0f}"]
                 for r in rows])
    if args.grasp:
        print_table("the tool's grasp in the hand against the hidden one (tool centre point)",
                    ["task", "seed", "poses", "tool", "steps", "fitted (mm)", "nominal (mm)",
                     "origin (mm)", "rotation (deg)", "LM kept", "seconds"],
                    [[r["task"], r["seed"], r["poses"], r["variant"].removeprefix("tool-"),
                      r["steps"], f"{r['grasp_tcp_err_mm']:.2f}",
                      f"{r['nominal_tcp_err_mm']:.2f}",
                      f"{r['grasp_pos_err_mm']:.2f}", f"{r['grasp_rot_err_deg']:.2f}",
                      {0: "Adam's", 1: "zero"}.get((r["grasp_refine"] or {}).get("start"), "-"),
                      f"{r['grasp_seconds']:.0f}"] for r in rows])
    print(f"wrote {args.out / 'hand_eye.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
