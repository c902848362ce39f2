"""Hand-eye calibration of an arm's camera mount and the tool's grasp in the hand, from real
RGB-D + segmentation frames (visual Real2Sim, ``twinrl.real2sim.visual``).

An arm task's camera sits on a mount the robot moves (``ArmTask.mount``, a ``CameraMount``); the
camera's true pose on it (the hand-eye offset) and the tool's true pose in the hand (the grasp)
are not known. ``calibrate_mount`` fits the offset so the differentiable renderer's images of the
recorded states, each from its frame's commanded mount pose, match the real frames;
``fit_grasp`` then fits the tool's offset with that camera held. The SAM-RL loop's ``calibrate``
stage runs both (``twinrl.loop.arm``); ``bench/hand_eye.py`` scores them against the hidden truth.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["calibrate_mount", "fit_grasp", "frame_cameras", "tool_geoms"]


def tool_geoms(model) -> list[int]:
    """Ids of the geoms of body ``tool`` and the bodies under it (the arm tasks' tool, held in
    the hand with a grasp the robot does not know exactly)."""
    from twinrl.real2sim.visual import body_geoms

    return body_geoms(model, "tool")


def calibrate_mount(env, frames, poses, config, seed: int = 0, *, ignore_tool: bool = True):
    """Hand-eye calibration of ``env``'s camera mount (``twinrl.real2sim.visual.fit_camera``)
    from real ``frames`` (checked, ``visual.check_frames``), frame ``i`` taken with the mount
    commanded to ``poses[i]`` (unconstrained coordinates): frames from one pose fit the camera
    there, turned into the offset (``CameraMount.with_hand_eye``); frames from several fit one
    offset, in each commanded camera's frame, to all of them. ``ignore_tool`` leaves the tool
    (``tool_geoms``) out: its grasp in the hand is not known, and on needle twin 0 its 7 mm /
    2 deg grasp error pulled the camera 3.8 mm / 0.24 deg off (0.33 mm / 0.015 deg without
    it). ``config``: a ``visual.VisualConfig``. Returns ``(mount, info)``."""
    from twinrl.real2sim import visual

    mount, model = env.mount, env.sim.mj_model
    poses = np.asarray(poses, np.float64)
    ignore = tool_geoms(model) if ignore_tool else ()
    cam, info = visual.fit_camera(model, frames, frame_cameras(mount, poses, frames), config,
                                  seed, ignore=ignore)
    if np.all(poses == poses[0]):  # the camera's pose there, turned into the offset
        return mount.with_hand_eye(cam, poses[0]), info
    return dataclasses.replace(mount, pos_offset=tuple(float(x) for x in info["pos_offset"]),
                               rot_offset=tuple(float(x) for x in info["rot_offset"])), info


def fit_grasp(env, mount, frames, poses, config, seed: int = 0) -> dict:
    """The tool's grasp in the hand (``visual.fit_body_offset`` of body ``tool``) from real
    ``frames``, frame ``i`` taken with the calibrated ``mount`` (``calibrate_mount``'s)
    commanded to ``poses[i]``. ``config``: a ``visual.VisualConfig``. Returns the fit's dict
    (``pos_offset``, ``rot_offset``: ``ArmTask.set_grasp``'s arguments)."""
    from twinrl.real2sim import visual

    cams = frame_cameras(mount, np.asarray(poses, np.float64), frames)
    return visual.fit_body_offset(env.sim.mj_model, frames, cams, "tool", config, seed)


def frame_cameras(mount, poses, frames):
    """``mount``'s camera (float64, the frames' size) at ``poses[i]`` for frame ``i``: one
    camera when every pose is the same, else a stack (one per frame)."""
    import jax

    from twinrl.render import Camera

    H, W = frames[0]["depth"].shape

    def camera(c):
        cam = mount.camera(np.asarray(c, np.float32), W, H)
        return Camera(np.asarray(cam.pos, np.float64), np.asarray(cam.quat, np.float64),
                      np.asarray(cam.fovy, np.float64), W, H)

    if np.all(poses == poses[0]):
        return camera(poses[0])
    return jax.tree_util.tree_map(lambda *a: np.stack(a), *[camera(c) for c in poses])
