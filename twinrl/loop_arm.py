"""The manipulation loop, SAM-RL's (Lv et al., RSS 2023): ``twinrl run --env peg_insertion``
(``needle_threading``, ``spatula_flipping``).

The robot has an arm that acts and a camera on a mount that it can move (``ArmTask.mount``); its
real twin (``twinrl.real.remote.TwinClient``) hides link masses, damping, friction, servo gains,
latency, observation noise, the camera's hand-eye offset and the tool's grasp in the hand. Round 0
records ``K`` episodes of small exciting motions seen from the mount's default pose (or from
several: ``ArmLoopConfig.calibration_poses``), each step's RGB-D + segmentation frame with it.
Every round ``r >= 1`` then runs these stages (``ARM_ROUND``, ``twinrl.loop.Stage`` values, so
a killed run resumes at the stage it was in):

1. **calibrate**: the mount camera's hand-eye calibration by visual Real2Sim -- the camera pose
   offset (in the commanded camera's frame) that makes the differentiable renderer's images of
   the recorded states, from each frame's commanded mount pose, match round 0's real frames
   (``twinrl.real2sim.visual.fit_camera`` with a stack of cameras; the tool, whose grasp is
   not known, left out), kept as the identified ``System``'s ``"mount"`` camera, so every later
   render and back-projection of the target uses it; then, with that camera, the tool's grasp
   in the hand (``visual.fit_body_offset``; ``ArmLoopConfig.grasp``: by default on the peg and
   the needle, where it was measured to help), kept as the ``System``'s
   ``objects["tool"]``, so the twin's tool, reward and success sit where the real tool does;
2. **sysid** (``ArmLoopConfig.sysid``): the action latency and the joints' servo gains and
   damping from round 0's transitions (``twinrl.real2sim.sysid``), else the nominal ones;
3. **plan**: trajectory-optimised demonstrations in the identified twin (``twinrl.learn.plans``);
4. **imitation**: the image actor cloned from them (``twinrl.learn.imitation``, demonstrations
   rendered from several mount poses): by default on the target's pose fitted to the mount's
   depth image (``ArmTask.fit_target_pose``, peg and needle) or on the target cloud's
   statistics (spatula);
5. **sensing**: the sensing-aware Q of that actor (``twinrl.learn.sensing``);
6. **residual** (``ArmLoopConfig.residual``; ``"pose"`` actors): SAM-RL's zero-initialised
   residual policy (``twinrl.sim2real.residual``), trained through the hybrid model -- the
   identified twin plus residual dynamics fitted to the recorded real transitions
   (``twinrl.sim2real.hybrid``) -- over whole episodes from the task's starts, the actor fed
   the pose estimate perfect perception would give (``active.pose_actor_on_state``: the model
   renders no images); trained only where the hybrid model predicts held-out real transitions
   better than the identified twin (else there is nothing real for it to correct), and kept
   only if it lowers the task's return neither through that model nor through the identified
   twin (``residual.accept``, no tolerance), else all zeros (the actor alone);
7. **deploy**: ``K`` real episodes: the camera chosen by Q's ascent through the renderer from the
   state read off the robot (``ArmLoopConfig.camera``), the mount moved there (its steps counted),
   the actor (plus the accepted residual) acting on the real frames; every transition recorded as
   it happens, with its frame.

Real success is the task's success of the twin's true final state (``TwinClient.success``: an
operator's verdict, recorded per episode, never learned from). Evaluation only, in ``OUT/eval/``
(which no stage reads): the calibration's error against the hidden hand-eye offset, and the same
actor deployed with the fixed default camera on ``eval_episodes`` unrecorded episodes (the
baseline the chosen camera must beat) and, when a residual was accepted, the actor without it
with the chosen camera on the same episodes (what the residual changed).

Resume, as ``twinrl.loop``: each stage marks itself done in ``progress.json`` after writing its
outputs; real episodes go to ``dataset/`` as they happen, so a run killed at any moment loses
nothing recorded, and a resumed deployment starts at its first unrecorded episode (episode ``i``
resets with seed ``seed + i``, so the episodes are those an uninterrupted run would have had).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from twinrl import eval as evaluation
from twinrl import report
from twinrl.loop import (LoopError, Progress, RunContext, Stage, episodes_in, quiet,
                         read_dataset, seconds_so_far)

__all__ = ["ArmLoopConfig", "make_config", "run", "ARM_COLLECT", "ARM_ROUND", "is_arm_task"]

def _imitation_defaults() -> dict[str, Any]:
    # demonstrations seen from 8 mount poses each; the observation and the DAgger rounds are the
    # task's (_observation, TASK_IMITATION), unless set
    return {"views": 8, "eval_episodes": 20}


TASK_IMITATION: dict[str, dict[str, Any]] = {
    "spatula_flipping": {"dagger_rounds": 4, "solved_labels": True},
}
"""Imitation settings a task's loop uses unless ``--set imitation.FIELD=...`` says otherwise
(other tasks: cloning alone, ``dagger_rounds=0``). The spatula's target-cloud actor needs DAgger:
on twin 1's identified twin (``bench/imitation.py --run``, H200, 50 starts the stage did not
choose on) 41 % after two rounds (three seeds), 74 % after four (two seeds); its loop with four
rounds and the grasp fit (``--set grasp=true``), 64 % on 50 real starts with the chosen camera,
66 % with the default (two rounds, the nominal grasp: 0/5 and 0/10 in the loop).
The needle's pose actor gains nothing lasting from DAgger (twin 1: 52 / 62 / 52 %)."""


def imitation_settings(config: ArmLoopConfig, env) -> dict[str, Any]:
    """The imitation stage's settings on ``env``: the task's (``TASK_IMITATION``, the
    observation) under the loop's ``imitation`` settings."""
    return {"dagger_rounds": 0, **TASK_IMITATION.get(env.name, {}), **dict(config.imitation),
            "observation": _observation(env, config.imitation)}


def _observation(env, imitation: Mapping[str, Any]) -> str:
    """The image actor's observation: the setting's, else ``"pose"`` where the task's target pose
    is fitted from the image (peg, needle), else ``"target"`` (the target cloud's statistics; the
    CNN on pixels reached 10-20 % in 25 min on 2 cores)."""
    return imitation.get("observation") or ("pose" if env.target_joints else "target")


def _sensing_defaults() -> dict[str, Any]:
    return {"states": 32, "cameras": 8, "restarts": 4, "ascent_steps": 15}


def _residual_defaults() -> dict[str, Any]:
    # whole episodes (the arm tasks' 50 steps) from the task's starts, as the gate judges it:
    # from the recorded exciting states (20 steps) the residual raised its own objective and
    # lowered the task's return, and was rejected (ResidualConfig.starts); 16 rollouts a step,
    # 60 steps: 1.2-1.5 s a step on 2 cores, after a 1-4 min compile (needle)
    return {"starts": "reset", "horizon": 50, "batch_size": 16, "steps": 60}


NESTED = ("imitation", "sensing", "residual_policy")
"""The settings ``make_config`` takes as ``NAME.FIELD=value`` (overrides of a stage's config)."""


@dataclasses.dataclass(frozen=True)
class ArmLoopConfig:
    """Settings of ``twinrl run`` on a manipulation task."""

    rounds: int = 1
    episodes_per_round: int = 5
    """Real episodes recorded per round (round 0: exciting motions; later: the deployment)."""
    calibrate: bool = True
    """Hand-eye calibration of the camera mount from round 0's frames."""
    calibration_frames: int = 10
    """Round-0 frames the calibration fits, evenly spread."""
    calibration_steps: int = 150
    """Adam steps of the calibration (``VisualConfig.steps``), before its Levenberg-Marquardt
    refinement."""
    calibration_poses: int = 1
    """Mount poses round 0's episodes are spread over (``CameraMount.calibration_poses``: the
    default pose first, then poses across the workspace); the calibration then fits one offset
    to the frames of every pose. From one pose a sideways shift of the camera and a turn of it
    give nearly the same image; measured on needle twin 0 (10 frames, the tool left out) one
    pose already gives 0.33 mm / 0.015 deg and five 0.46 mm / 0.040 deg, so the default stays
    at one (no camera moves in round 0)."""
    calibration_restarts: int = 1
    """Random restarts of the calibration (``VisualConfig.restarts``). One, from the nominal
    pose: a hand-eye offset is small (peg twin 3: 3.4 cm, 1.1 deg), and the nominal start alone
    finds it to 0.6 mm / 0.04 deg, where 3 restarts took 273 s on 2 cores."""
    grasp: bool | None = None
    """After the calibration, identify the tool's grasp in the hand from the same frames
    (``visual.fit_body_offset`` on body ``tool``, the calibrated camera held), kept as the
    ``System``'s ``objects["tool"]`` (``ArmTask.set_grasp``): the twin's tool, its reward and its
    success then sit where the real tool does. Needs ``calibrate``. ``None`` (the default): on for
    the tasks where it was measured to help (``GRASP_TASKS``), off elsewhere. Spatula: the
    tool point 2.40 / 2.05 / 2.09 mm off on twins 0-2 against 4.56 / 13.14 / 10.95 nominal
    (stop 58); twin 1's loop with it (and four DAgger rounds) 64 / 66 % on 50 real starts with
    the chosen / default camera, where with the nominal grasp 0/5 and 0/10; twin 2's loop with
    it solved 0 of 48 plans (stop 59) until the controller was calibrated
    (``calibrate_controller``; stop 61: 45 of 48, and twin 1's loop 5/5 and 9/10). The tool point
    against the truth (``bench/hand_eye.py --grasp``, stop 57):
    needle twins 0-2 2.68 / 3.42 / 1.94 mm (nominal: 8.70 / 4.36 / 2.10; stop 55's run of the same
    fit: 0.81 / 3.10 / 1.15), peg twins 0-2 0.66 / 1.13 / 0.77 mm (nominal: 5.78 / 12.21 / 10.61).
    Peg twins 1 and 2, 50 real starts: 88 and 80 % with the chosen camera (twin 1's loop with the
    nominal grasp: 2/5 chosen, 5/10 default)."""
    sysid: bool = True
    """Identify the action latency and the arm's servo dynamics (joint gains and damping) from
    round 0's transitions (``_sysid_config``; 4 min on 2 cores). On needle twin 2 the twin's
    hidden latency, gains, damping and noise cost the chosen camera 24 points from sim to real
    (94 -> 70 %); identified (latency right, gains within 0.5-16 %), 90 -> 84 %. The masses
    are left nominal: the servo-tracked motions barely show them (fitted, link 2's came out
    7x its truth there)."""
    calibrate_controller: bool = True
    """Calibrate the Cartesian controller to the identified servos (``ArmTask.servo_speed``,
    kept as the ``System``'s ``objects["controller"]``) in the identified twin and on the real
    arm (``RealTwin.calibrate_controller``, set by the deployment) from round 1 on; round 0
    records with the nominal controller, and sysid and the hybrid model fit round 0's episodes
    under it. The controller sets targets a step from the measured joints, so each joint moves
    at its servo's gain over damping: a twin's +-15 % servos bend the commanded motion (spatula
    twin 2: a lift 31 degrees off, 74 % as far) and its plans fail even with the true parameters
    (0/8); calibrated with the true speeds 8/8, with the identified ones 6/8 (README, stop 61)."""
    demonstrations: int = 48
    """Random starts trajectory optimisation plans from (the solved ones are demonstrations)."""
    trajopt_iterations: int = 20
    trajopt_restarts: int = 2
    imitation: Mapping[str, Any] = dataclasses.field(default_factory=_imitation_defaults)
    """``ImitationConfig`` overrides of the image actor."""
    sensing: Mapping[str, Any] = dataclasses.field(default_factory=_sensing_defaults)
    """``SensingConfig`` overrides of the sensing-aware Q."""
    camera: str = "selected"
    """The deployment's camera: ``"selected"`` (Q's ascent), ``"default"`` or ``"random"``."""
    camera_min_rank: float = 0.2
    """``"selected"`` deploys Q's choice only if Q's rank correlation on its held-out states
    (the sensing stage's ``rank_corr``) reaches this; below it the round deploys the default
    camera and says so (``deployed_camera``). On 50 real starts per twin (stops 55-61): Q at
    0.38-0.62 chose as well as the default or better (spatula twin 1 +0, needle +8 .. +18),
    peg at 0.33 -2; spatula twin 2's Q at -0.12 cost 20 points (76 against 96 %), twin 0's at
    0.02 cost 6 (84 against 90 %, stop 62)."""
    eval_episodes: int = 10
    """Evaluation-only real episodes (not recorded) of the deployed actor with the default
    camera; 0: none."""
    residual: bool = True
    """Train a residual policy on the actor through the hybrid model and deploy it if
    ``residual.accept`` accepts it (the module's stage 6; ``"pose"`` actors only: for others the
    stage says so and deploys the actor alone)."""
    residual_policy: Mapping[str, Any] = dataclasses.field(default_factory=_residual_defaults)
    """``ResidualConfig`` overrides of the residual policy."""
    residual_min_model_gain: float = 0.05
    """The residual is trained only if the hybrid model's one-step error on held-out real
    episodes (mean RMSE over the state) is at least this fraction below the identified twin's:
    a model no better than the twin gives a residual nothing real to correct, only the twin to
    re-fit. On round 0's transitions of needle twins 0-2 (sysid on) the gain is +3.9, 0.0 and
    0.0 %. On twin 2 (the run's 500 transitions: the hybrid's 0.0068 against the twin's 0.0067)
    a residual trained anyway (whole episodes from the task's starts) passed the gate (return
    +1.1 % through the hybrid model, -0.8 % through the twin) and cost the chosen camera 10
    real points (84 -> 74 %, 50 episodes: 5 solved only without it, 0 only with it)."""
    video: bool = True
    """Write final.mp4: a deployment episode, the deployed view beside an overview of the scene."""
    image_size: int | None = None
    """Width and height (pixels) of the mount camera's images, recorded, simulated and deployed;
    ``None``: the task's (``ArmConfig.image_size``). The needle at 128 instead of its 64: the
    image actor 74-86 % from random views where 64 gave 50-75 %, and the default camera then
    solves 88-100 % of real starts (docs/manipulation_loop.md, "The needle at 128x128")."""

    def __post_init__(self):
        for name in ("rounds", "episodes_per_round", "calibration_frames", "calibration_steps",
                     "calibration_poses", "calibration_restarts", "demonstrations",
                     "trajopt_iterations"):
            if int(getattr(self, name)) < 1:
                raise LoopError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.residual_min_model_gain < 1.0:
            raise LoopError(f"residual_min_model_gain must be in [0, 1), got "
                            f"{self.residual_min_model_gain}")
        for name in ("trajopt_restarts", "eval_episodes"):
            if int(getattr(self, name)) < 0:
                raise LoopError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.grasp is not None and not isinstance(self.grasp, bool):
            raise LoopError(f"grasp must be true, false or null (the task's default), got "
                            f"{self.grasp!r}")
        if not -1.0 <= self.camera_min_rank <= 1.0:
            raise LoopError(f"camera_min_rank must be in [-1, 1] (a rank correlation), got "
                            f"{self.camera_min_rank}")
        if self.image_size is not None and (isinstance(self.image_size, bool)
                                            or not isinstance(self.image_size, int)
                                            or self.image_size < 16):
            raise LoopError(f"image_size must be an integer >= 16 or null (the task's), got "
                            f"{self.image_size!r}")
        if self.camera not in ("selected", "default", "random"):
            raise LoopError(f"camera must be 'selected', 'default' or 'random', got "
                            f"{self.camera!r}")
        from twinrl.learn.imitation import ImitationConfig
        from twinrl.learn.sensing import SensingConfig
        from twinrl.sim2real.residual import ResidualConfig

        for cls, name in ((ImitationConfig, "imitation"), (SensingConfig, "sensing"),
                          (ResidualConfig, "residual_policy")):
            try:
                cls(**dict(getattr(self, name)))
            except (TypeError, ValueError) as e:
                raise LoopError(f"{name}: {e}") from None
        if dict(self.imitation).get("observation") == "state":
            raise LoopError("imitation: the loop deploys an image actor; observation must be "
                            "'pose', 'target' or 'pixels'")


def task_env(env_name: str, config: ArmLoopConfig, system=None, **settings):
    """The task's ``Env`` as the loop runs it (``system``: a ``System``, default nominal; the
    loop's ``image_size`` where it sets one; ``settings``: other ``ArmConfig`` fields)."""
    from twinrl import envs

    if config.image_size is not None:
        settings = {"image_size": int(config.image_size), **settings}
    return envs.make(env_name, system=system, **settings)


def run_env(run_dir: str | Path, system=None, **settings):
    """``task_env`` of a ``twinrl run`` output directory (its ``loop.json``: the task and the
    settings it ran with), for benches and tools that rebuild the run's twin. A run without an
    ``image_size`` setting (older ones too) runs at the task's."""
    saved = json.loads((Path(run_dir) / "loop.json").read_text())
    size = (saved.get("config") or {}).get("image_size")
    return task_env(saved["env"], ArmLoopConfig(image_size=size), system, **settings)


GRASP_TASKS = ("peg_insertion", "needle_threading", "spatula_flipping")
"""The tasks whose loop identifies the tool's grasp by default (``ArmLoopConfig.grasp``)."""


def grasp_on(config: ArmLoopConfig, env_name: str) -> bool:
    """Whether the loop identifies the tool's grasp on ``env_name`` (``ArmLoopConfig.grasp``:
    ``None`` means on for ``GRASP_TASKS`` only)."""
    return env_name in GRASP_TASKS if config.grasp is None else bool(config.grasp)


def make_config(overrides: Mapping[str, Any] | None = None) -> ArmLoopConfig:
    """``ArmLoopConfig`` with ``overrides`` (``twinrl run --set``): ``field=value``, and
    ``imitation.FIELD=value`` / ``sensing.FIELD=value`` / ``residual_policy.FIELD=value`` into
    those stages' settings (added to the defaults)."""
    names = {f.name for f in dataclasses.fields(ArmLoopConfig)}
    flat: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {k: {} for k in NESTED}
    for k, v in (overrides or {}).items():
        head, _, rest = k.partition(".")
        if head not in names or (rest and head not in nested):
            raise LoopError(f"the manipulation loop has no setting {k!r}; settings: "
                            f"{', '.join(sorted(names))} (and "
                            f"{', '.join(k + '.FIELD' for k in NESTED)})")
        if rest:
            nested[head][rest] = tuple(v) if isinstance(v, list) else v
        else:
            flat[head] = v
    base = ArmLoopConfig.__dataclass_fields__
    for head, more in nested.items():
        if more:
            flat[head] = {**dict(flat.get(head) or base[head].default_factory()), **more}
    try:
        return ArmLoopConfig(**flat)
    except TypeError as e:
        raise LoopError(str(e)) from None


def is_arm_task(env_name: str) -> bool:
    """Whether ``env_name`` is a manipulation task (an ``ArmTask``): ``twinrl run`` runs this
    loop on it."""
    from twinrl import envs
    from twinrl.envs.arm.base import ArmTask

    return issubclass(envs.registry.TASKS[env_name].env_class, ArmTask)


# ------------------------------------------------------------------------------ the stages
def _collect(run: RunContext, r: int, rdir: Path) -> None:
    """Round 0: ``K`` episodes of exciting motions (``record_round0``), recorded with every
    step's frame (those the dataset already holds are not recorded again)."""
    K = run.K
    have = episodes_in(run.out / "dataset")
    run.say(f"[bold]round 0[/]: recording {K - have} exciting episodes with images"
            f"{f' ({have} already recorded)' if have else ''}")
    t0 = time.perf_counter()
    camera_steps = record_round0(run.twin, run.writer, run.nominal_env, run.seed,
                                 _round0_poses(run), range(have, K))
    run.prog.mark("round0/collect", real_steps=int(len(read_dataset(run.out / "dataset"))),
                  camera_steps=camera_steps, seconds={"collect": time.perf_counter() - t0})


def record_round0(twin, writer, env, seed: int, poses, episodes) -> int:
    """The loop's round-0 episodes ``episodes`` on ``twin`` (reset with seed ``seed + e``, the
    exciting motions ``sysid.excitation_actions`` draws for ``[seed, e]``), episode ``e`` seen
    from the mount at ``poses[e]``, recorded with every step's frame by ``writer``; the mount
    goes back to its default pose at the end. Returns the camera moves' steps."""
    from twinrl.real.twin import record_episode
    from twinrl.real2sim import sysid

    T, steps = env.episode_length, 0
    for e in episodes:
        acts = sysid.excitation_actions(np.random.default_rng([seed, e]), T, env.action_size)
        obs, _ = twin.reset(seed=seed + e)
        steps += int(twin.move_camera(poses[e]))
        record_episode(twin, writer, lambda o, t, a=acts: a[min(t, T - 1)], obs, images=True)
    return steps + int(twin.move_camera(env.mount.default))


def tool_geoms(model) -> list[int]:
    """Ids of the geoms of body ``tool`` and the bodies under it (the arm tasks' tool, held in
    the hand with a grasp the robot does not know exactly)."""
    from twinrl.real2sim.visual import body_geoms

    return body_geoms(model, "tool")


def _round0_poses(run: RunContext) -> np.ndarray:
    """The mount pose (unconstrained coordinates) of each round-0 episode: the
    ``calibration_poses`` poses in turn."""
    poses = run.nominal_env.mount.calibration_poses(run.config.calibration_poses)
    return poses[np.arange(run.K) % len(poses)]


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
    cam, info = visual.fit_camera(model, frames, _frame_cameras(mount, poses, frames), config,
                                  seed, ignore=ignore)
    if np.all(poses == poses[0]):  # the camera's pose there, turned into the offset
        return mount.with_hand_eye(cam, poses[0]), info
    return dataclasses.replace(mount, pos_offset=tuple(float(x) for x in info["pos_offset"]),
                               rot_offset=tuple(float(x) for x in info["rot_offset"])), info


def _calibrate(run: RunContext, r: int, rdir: Path, data) -> None:
    """Hand-eye calibration from round 0's frames, each seen from its episode's mount pose ->
    ``calibration.json`` (the fitted offset, and the camera it gives at the default pose)."""
    from twinrl.real2sim import visual

    env = run.nominal_env
    frames = visual.frames_from_dataset(run.env_name, data, run.config.calibration_frames,
                                        episodes=range(run.K))
    poses = _round0_poses(run)[[f["episode"] for f in frames]]
    frames = visual.check_frames(frames, env.sim.mj_model.nq)
    H, W = frames[0]["depth"].shape
    run.say(f"  hand-eye calibration on {len(frames)} real frames from "
            f"{len(np.unique(poses, axis=0))} mount pose(s) ...")
    t0 = time.perf_counter()
    cfg = visual.VisualConfig(steps=run.config.calibration_steps,
                              restarts=run.config.calibration_restarts)
    mount, info = calibrate_mount(env, frames, poses, cfg, run.seed + r)
    cam = mount.camera(np.asarray(mount.default, np.float32), W, H)
    grasp, errors = None, {}
    if grasp_on(run.config, run.env_name):
        run.say("  the tool's grasp in the hand, from the same frames ...")
        g = fit_grasp(env, mount, frames, poses, cfg, run.seed + r)
        grasp = {"pos_offset": g["pos_offset"], "rot_offset": g["rot_offset"],
                 "loss": min(x["final_loss"] for x in g["runs"]), "refine": g["refine"]}
        errors = evaluation.grasp_errors(run.env_name, run.seed, g["pos_offset"],
                                         g["rot_offset"], run.perturbation, run.secret)
    report.write_json(rdir / "calibration.json", {
        "camera": {"pos": np.asarray(cam.pos), "quat": np.asarray(cam.quat),
                   "fovy": np.asarray(cam.fovy), "width": W, "height": H},
        "pos_offset": mount.pos_offset, "rot_offset": mount.rot_offset, "frames": len(frames),
        "poses": len(np.unique(poses, axis=0)),
        "loss": min(x["final_loss"] for x in info["runs"]), "grasp": grasp})
    run.ev.mark(f"round{r}/calibrate", **evaluation.hand_eye_errors(
        run.env_name, run.seed, mount, run.perturbation, run.secret), **errors)
    run.prog.mark(f"round{r}/calibrate",
                  seconds=seconds_so_far(run.prog, r, calibrate=time.perf_counter() - t0))


def fit_grasp(env, mount, frames, poses, config, seed: int = 0) -> dict:
    """The tool's grasp in the hand (``visual.fit_body_offset`` of body ``tool``) from real
    ``frames``, frame ``i`` taken with the calibrated ``mount`` (``calibrate_mount``'s)
    commanded to ``poses[i]``. ``config``: a ``visual.VisualConfig``. Returns the fit's dict
    (``pos_offset``, ``rot_offset``: ``ArmTask.set_grasp``'s arguments)."""
    from twinrl.real2sim import visual

    cams = _frame_cameras(mount, np.asarray(poses, np.float64), frames)
    return visual.fit_body_offset(env.sim.mj_model, frames, cams, "tool", config, seed)


def _frame_cameras(mount, poses, frames):
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


def _load_camera(run: RunContext, rdir: Path, data) -> dict[str, Any]:
    from twinrl.render import Camera

    f = rdir / "calibration.json"
    if not run.config.calibrate or not f.exists():
        return {"camera": None, "grasp": None}
    doc = json.loads(f.read_text())
    c = doc["camera"]
    return {"camera": Camera(np.asarray(c["pos"]), np.asarray(c["quat"]),
                             np.asarray(c["fovy"]), int(c["width"]), int(c["height"])),
            "grasp": doc.get("grasp")}


def _system(run: RunContext, r: int, rdir: Path, data, camera, grasp=None) -> None:
    """The identified ``System`` -> ``system.json``: sysid's parameters and latency (or the
    nominal ones) with the calibrated mount camera and the tool's identified grasp."""
    from twinrl.envs.system import System

    t0 = time.perf_counter()
    system = System.nominal(run.env_name)
    if run.config.sysid:
        from twinrl.real2sim import sysid

        fitted = nominal_episodes(run, data)
        run.say(f"  sysid on {len(fitted)} real transitions ...")
        res = sysid.fit(run.nominal_env, fitted, _sysid_config())
        system = res.system
        run.ev.mark(f"round{r}/sysid", **evaluation.sysid_errors(
            run.nominal_env, res, run.env_name, run.seed, run.perturbation, run.secret))
    if camera is not None:
        system = system.replace(cameras={"mount": camera})
    objects = {}
    if grasp is not None:
        objects["tool"] = {k: np.asarray(grasp[k], np.float64)
                           for k in ("pos_offset", "rot_offset")}
    if run.config.sysid and run.config.calibrate_controller:
        objects["controller"] = {"joint_speed": run.nominal_env.servo_speed(system.params)}
    if objects:
        system = system.replace(objects=objects)
    system.save(rdir / "system.json")
    run.prog.mark(f"round{r}/sysid", latency=system.latency,
                  seconds=seconds_so_far(run.prog, r, sysid=time.perf_counter() - t0))


def nominal_episodes(run: RunContext, data):
    """The real episodes recorded with the nominal controller, which the fits of real
    transitions (sysid, the hybrid model) simulate them with: all of them, or, with the
    controller calibrated from round 1 on (``ArmLoopConfig.calibrate_controller``), round 0's."""
    if run.config.sysid and run.config.calibrate_controller:
        return data.first_episodes(run.K)
    return data


def uncalibrated(env):
    """``env`` (an arm task, or a wrapper of one) with the nominal controller: a copy, ``env``
    itself untouched."""
    inner = getattr(env, "env", None)
    if inner is not None:  # a wrapper (the latency's): the same around an uncalibrated task
        out = copy.copy(env)
        out.env = uncalibrated(inner)
        return out
    if getattr(getattr(env, "controller", None), "joint_speed", None) is None:
        return env
    out = copy.copy(env)
    out.calibrate_controller(None)
    return out


def _sysid_config():
    """The arm's sysid: latency 0-1 and the 7 joints' servo gains and damping (what the
    exciting motions show; ``panda.xml`` names joints and servos ``joint1``..``joint7``);
    15 Levenberg-Marquardt steps per latency (it had converged by 10 on needle twin 2), no
    bound tests (damping is far from 0). Windows start from the recorded states: the joints
    are measured to 2 mrad, and on spatula twin 0 the parameters come within 0.7-18 % of the
    truth in 166 s. Estimating every window's start as well (31 numbers a window there) stalled
    until stop 53 (the pancake's unseen spin took absurd LM steps; now held by the starts'
    prior); fixed, it gives 0.3-17 %, far slower (README: the arm's sysid).

    The parameters' prior stays sysid's weak default (3). The data pin the gains loosely: on
    spatula twin 2 their sd from 300 transitions is 13-39 % and the fit lands 17-44 % off
    there, gain and damping of a joint off by about one factor (joint 1: 0.75 and 0.76): the
    controller's targets are the measured joints plus a step, so a joint's speed shows its
    gain over its damping, their common scale only through gravity and inertia. A datasheet
    prior (``prior_sd=0.2``) bounds that (18 % there, 21 % on twin 1 against 29 %) but costs
    where the data do speak (needle twin 2: largest error 9.4 -> 13.4 %, median 3.2 -> 5.8 %),
    and twin 2's plans failed with the true parameters as well (README, stop 60) until the
    controller was calibrated to the servo speeds, which the data do pin (stop 61);
    ``bench/arm_sysid.py --prior-sd`` measures it."""
    from twinrl.envs.arm.base import N_JOINTS
    from twinrl.real2sim import sysid

    names = tuple(f"{f}/joint{i}" for f in ("damping", "gain") for i in range(1, N_JOINTS + 1))
    return sysid.SysidConfig(params=names, lm_steps=15, bound_lr=0.0, estimate_start=False)


def _load_system(run: RunContext, rdir: Path, **_) -> dict[str, Any]:
    from twinrl.envs.system import System

    system = System.load(rdir / "system.json")
    return {"system": system, "env": task_env(run.env_name, run.config, system)}


def _plan(run: RunContext, r: int, rdir: Path, env) -> None:
    """Trajectory-optimised demonstrations in the identified twin -> ``plans.npz``."""
    from twinrl.learn import plans

    c = run.config
    run.say(f"  planning {c.demonstrations} demonstrations in the identified twin ...")
    t0 = time.perf_counter()
    res = plans.plan(env, c.demonstrations, c.trajopt_iterations, min(10, c.demonstrations),
                     run.seed + r, restarts=c.trajopt_restarts)
    plans.save(rdir / "plans.npz", res)
    solved = int(np.sum(np.asarray(res["success"])))
    if solved < 0.25 * c.demonstrations:  # the actor learns from these alone
        run.say(f"  [yellow]only {solved} of {c.demonstrations} plans solved the task in the "
                f"identified twin[/] (trajopt_iterations={c.trajopt_iterations}, "
                f"trajopt_restarts={c.trajopt_restarts})")
    run.prog.mark(f"round{r}/plan", plan_success=res["success_rate"],
                  seconds=seconds_so_far(run.prog, r, plan=time.perf_counter() - t0))


def _imitate(run: RunContext, r: int, rdir: Path, env) -> None:
    """The image actor cloned from the demonstrations -> ``actor/``."""
    from twinrl.learn.runner import continue_run

    run.say("  cloning the image actor ...")
    t0 = time.perf_counter()
    overrides = {**imitation_settings(run.config, env), "demonstrations": str(rdir / "plans.npz")}
    s = continue_run(run.env_name, "imitation", rdir / "actor", seed=run.seed + r,
                     overrides=overrides, progress=run.progress, env=env)
    run.prog.mark(f"round{r}/imitation", sim_success=s["final"].get("success"),
                  seconds=seconds_so_far(run.prog, r, imitation=time.perf_counter() - t0))


def _sense(run: RunContext, r: int, rdir: Path, env) -> None:
    """The sensing-aware Q of the actor -> ``q/``."""
    from twinrl.learn.runner import continue_run

    run.say("  learning the sensing-aware Q ...")
    t0 = time.perf_counter()
    overrides = {**dict(run.config.sensing), "actor": str(rdir / "actor")}
    s = continue_run(run.env_name, "sensing", rdir / "q", seed=run.seed + r,
                     overrides=overrides, progress=run.progress, env=env)
    run.prog.mark(f"round{r}/sensing", q_rank_corr=s["final"].get("rank_corr"),
                  q_rank_corr_pooled=s["final"].get("rank_corr_pooled"),
                  seconds=seconds_so_far(run.prog, r, sensing=time.perf_counter() - t0))


def _residual(run: RunContext, r: int, rdir: Path, env, system, data) -> None:
    """The hybrid model (``hybrid/``) and the residual policy through it (``residual/``: the
    trained one if ``residual.accept`` keeps it, else all zeros, exactly the actor)."""
    import jax

    from twinrl.learn.checkpoint import save_policy
    from twinrl.learn.sensing import load_actor
    from twinrl.sim2real import active, hybrid, residual

    t0 = time.perf_counter()
    actor, actor_params, _ = load_actor(rdir / "actor")
    if set(actor.obs_spec) != {"estimate"}:
        run.say(f"  no residual policy: the actor reads {', '.join(sorted(actor.obs_spec))}, "
                f"which the hybrid model cannot render (a 'pose' actor can have one)")
        run.prog.mark(f"round{r}/residual", residual_accepted=None)
        return
    seed = run.seed + r
    # the transitions under the controller that recorded them; the model's correction then
    # rides on the calibrated twin (``make_dynamics``)
    fitted = nominal_episodes(run, data)
    run.say(f"  fitting the hybrid dynamics to {len(fitted)} real transitions ...")
    fit = hybrid.fit(uncalibrated(env), fitted, latency=system.latency,
                     rng=jax.random.key(seed))
    hybrid.save(rdir / "hybrid", fit)
    errors = {"hybrid_sim_rmse": float(np.mean(fit.metrics["sim_val_rmse"])),
              "hybrid_rmse": float(np.mean(fit.metrics["hybrid_val_rmse"]))}
    gain = 1.0 - errors["hybrid_rmse"] / max(errors["hybrid_sim_rmse"], 1e-12)
    if not gain >= run.config.residual_min_model_gain:
        run.say(f"  no residual policy: the hybrid model predicts held-out real transitions "
                f"{100 * gain:+.1f} % better than the identified twin (RMSE "
                f"{errors['hybrid_rmse']:.4g} against {errors['hybrid_sim_rmse']:.4g}; "
                f"residual_min_model_gain {run.config.residual_min_model_gain:g})")
        run.prog.mark(f"round{r}/residual", residual_accepted=None, **errors,
                      seconds=seconds_so_far(run.prog, r, residual=time.perf_counter() - t0))
        return
    dynamics = hybrid.make_dynamics(env, fit.model)
    cfg = residual.ResidualConfig(**dict(run.config.residual_policy))
    pol = residual.make_residual(active.pose_actor_on_state(env, actor), actor_params, cfg)
    run.say("  training the residual policy through the hybrid model ...")
    # no tolerance on the twin: a precision task's success turns on millimetres
    params, metrics, v = residual.train_gated(env, dynamics, pol, data.obs, cfg, seed,
                                              tolerance=0.0)
    run.say(f"  residual {'accepted' if v.accepted else 'rejected (deploying the actor alone)'}"
            f": return through the hybrid model {v.before:.2f} -> {v.after:.2f}, the identified "
            f"twin {v.reference_before:.2f} -> {v.reference_after:.2f}")
    save_policy(rdir / "residual", pol.delta, params, kind="residual", metrics=metrics)
    run.prog.mark(f"round{r}/residual", residual_accepted=v.accepted, **errors,
                  residual_model_return=[v.before, v.after],
                  residual_sim_return=[v.reference_before, v.reference_after],
                  seconds=seconds_so_far(run.prog, r, residual=time.perf_counter() - t0))


def _deployer(run: RunContext, env, rdir: Path, r: int, residual: bool = True):
    """The round's ``Deployer``: its actor, its Q (camera ``"selected"``) and, when ``residual``
    and the round's residual was accepted, that residual."""
    from twinrl.learn.sensing import SensingConfig, load_actor
    from twinrl.sense import load_q
    from twinrl.sim2real.active import Deployer, residual_correction

    actor, actor_params, _ = load_actor(rdir / "actor")
    q = q_params = sensing = correction = None
    if run.config.camera == "selected":
        q, q_params, meta = load_q(rdir / "q")
        sensing = SensingConfig.from_dict(meta.get("config") or {})
    if residual and run.prog.record(r).get("residual_accepted"):
        from twinrl.learn.checkpoint import load_policy

        delta, params, _ = load_policy(rdir / "residual")
        correction = residual_correction(delta, params)
    return Deployer(env, actor, actor_params, q=q, q_params=q_params, sensing=sensing,
                    residual=correction)


def deployed_camera(run: RunContext, r: int) -> str:
    """Round ``r``'s deployment camera: ``config.camera``, except ``"selected"`` falls back to
    ``"default"`` where Q ranked its held-out states below ``camera_min_rank`` (or was not
    scored)."""
    c = run.config
    if c.camera != "selected":
        return c.camera
    rank = run.prog.record(r).get("q_rank_corr")
    ok = rank is not None and np.isfinite(rank) and rank >= c.camera_min_rank
    return "selected" if ok else "default"


def _deploy(run: RunContext, r: int, rdir: Path, env) -> None:
    """``K`` real episodes of the image actor with the chosen camera, recorded as they happen
    (a resumed deployment starts at its first unrecorded episode); then, evaluation only, the
    same actor with the fixed default camera on ``eval_episodes`` unrecorded episodes."""
    from twinrl.sim2real.active import DeployConfig

    prog, K = run.prog, run.K
    t0 = time.perf_counter()
    deployer = _deployer(run, env, rdir, r)
    rows = list(prog.record(r).get("deploy_partial", []))
    have = len(rows)
    camera = deployed_camera(run, r)
    if camera != run.config.camera:
        rank = prog.record(r).get("q_rank_corr")
        rank = "not scored" if rank is None else f"{rank:.2f}"
        run.say(f"  [yellow]deploying the default camera[/]: Q's rank correlation on its "
                f"held-out states ({rank}) is below camera_min_rank {run.config.camera_min_rank:g}")
    run.say(f"  deploying on the real twin ({K - have} episodes, camera {camera}) ...")
    cfg = DeployConfig(camera=camera, episodes=K)

    def keep(row):
        rows.append(report.to_jsonable(row))
        prog.mark(f"round{r}/deploy_partial", deploy_partial=rows)

    deployer.run(run.twin, cfg, seed=1000 * r + run.seed, start=have, writer=run.writer,
                 on_episode=keep)
    t_eval = time.perf_counter()
    if run.config.eval_episodes:
        base = evaluation.deployed_success(
            run.env_name, run.seed, deployer, DeployConfig(camera="default",
                                                           episodes=run.config.eval_episodes),
            run.perturbation, run.secret, size=run.twin.width)
        run.ev.mark(f"round{r}/deploy", default_camera_success=base["success_rate"],
                    default_camera_successes=base["success"])
        if deployer.residual is not None:  # what the residual changed, on the same episodes
            cfg = DeployConfig(camera=camera, episodes=run.config.eval_episodes)
            rows_eval = {name: evaluation.deployed_success(
                run.env_name, run.seed, d, cfg, run.perturbation, run.secret,
                size=run.twin.width)["success"]
                for name, d in (("with", deployer),
                                ("without", _deployer(run, env, rdir, r, residual=False)))}
            run.ev.mark(f"round{r}/deploy", residual_eval_successes=rows_eval["with"],
                        no_residual_eval_successes=rows_eval["without"])
    prog.mark(f"round{r}/deploy", deployed_camera=camera,
              real_success=float(np.mean([x["success"] for x in rows])),
              real_successes=[x["success"] for x in rows],
              real_return=float(np.mean([x["return"] for x in rows])),
              camera_steps=int(sum(x["camera_steps"] for x in rows)),
              chosen_coords=[x["coords"] for x in rows],
              real_steps=int(len(read_dataset(run.out / "dataset"))),
              seconds=seconds_so_far(prog, r, deploy=t_eval - t0,
                               evaluation=time.perf_counter() - t_eval))


ARM_COLLECT = Stage("collect", needs=(), gives=(), make=_collect)
"""Round 0's stage."""

ARM_ROUND = (
    Stage("calibrate", needs=("data",), gives=("camera", "grasp"), make=_calibrate,
          load=_load_camera, enabled=lambda c: c.calibrate),
    Stage("sysid", needs=("data", "camera", "grasp"), gives=("system", "env"), make=_system,
          load=_load_system),
    Stage("plan", needs=("env",), gives=(), make=_plan),
    Stage("imitation", needs=("env",), gives=(), make=_imitate),
    Stage("sensing", needs=("env",), gives=(), make=_sense,
          enabled=lambda c: c.camera == "selected"),
    Stage("residual", needs=("env", "system", "data"), gives=(), make=_residual,
          enabled=lambda c: c.residual),
    Stage("deploy", needs=("env",), gives=(), make=_deploy),
)
"""The stages of every round ``r >= 1``, in order."""


# ------------------------------------------------------------------------------ the run
def run(env_name: str, out: str | Path, config: ArmLoopConfig = ArmLoopConfig(), *,
        seed: int = 0, resume: bool = False, progress: bool = True,
        perturbation=None) -> dict[str, Any]:
    """Run the manipulation loop on ``env_name``'s real twin (hidden perturbation drawn from
    ``seed``) into ``out``; returns the summary (also ``out/summary.json``)."""
    from twinrl.loop import check_settings

    if not is_arm_task(env_name):
        raise LoopError(f"{env_name!r} is not a manipulation task (twinrl.loop runs it)")
    out = check_settings(env_name, Path(out), config, seed, resume)
    ctx = _start(env_name, out, config, seed, progress, perturbation)
    rounds = []
    try:
        ARM_COLLECT(ctx, 0, {})
        rounds.append(_round_record(ctx, 0))
        for r in range(1, config.rounds + 1):
            ctx.say(f"[bold]round {r}[/] ({time.perf_counter() - ctx.t_start:.0f} s)")
            artefacts = {"data": read_dataset(out / "dataset", ctx.say)}
            for stage in ARM_ROUND:
                artefacts.update(stage(ctx, r, artefacts))
            rounds.append(_round_record(ctx, r))
    finally:
        ctx.close()
    return _finish(ctx, rounds)


def _start(env_name, out, config, seed, progress, perturbation) -> RunContext:
    from twinrl.real.dataset import DatasetMismatch, DatasetWriter
    from twinrl.real.remote import TwinClient

    say = report.console.print if progress else quiet
    t_start = time.perf_counter()
    ev_dir = out / "eval"
    secret = ev_dir / "twin.json"
    env = task_env(env_name, config)
    n = int(env.config.image_size)
    twin = TwinClient(env_name, seed=seed, secret=secret, perturbation=perturbation, width=n,
                      height=n)
    obs0, _ = twin.reset(seed=seed)
    shapes = {"rgb": (n, n, 3), "depth": (n, n), "segmentation": (n, n)}
    try:
        writer = DatasetWriter(out / "dataset", env=env_name, obs_shape=obs0.shape,
                               action_shape=twin.action_space.shape, obs_dtype=np.float32,
                               action_dtype=np.float32, image_shapes=shapes)
    except ValueError as e:  # a dataset recorded with other shapes (an older twinrl's images)
        twin.close()
        why = (f". This twinrl's {env_name} records {n}x{n} images (ArmConfig.image_size); "
               f"resume with the version that started the run"
               if isinstance(e, DatasetMismatch) and e.key == "image_shapes" else "")
        raise LoopError(f"{e}{why}") from None
    return RunContext(env_name, int(seed), out, config, perturbation, secret, twin, writer,
                Progress(out / "progress.json"), Progress(ev_dir / "evaluation.json"), say,
                progress, env, t_start)


def _round_record(run: RunContext, r: int) -> dict[str, Any]:
    rec = run.prog.record(r)
    keys = ("real_steps", "real_success", "real_successes", "real_return", "camera_steps",
            "chosen_coords", "plan_success", "sim_success", "q_rank_corr", "q_rank_corr_pooled",
            "latency", "residual_accepted", "hybrid_rmse", "hybrid_sim_rmse", "deployed_camera",
            "seconds")
    return {"round": r, **{k: rec.get(k) for k in keys}}


def _finish(run: RunContext, rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """The evaluation records merged into the rounds; ``summary.json``, the table, the plot and
    the video."""
    for rec in rounds:
        rec.update(run.ev.record(rec["round"]))
    real_episodes = run.K * (run.config.rounds + 1)
    final = dict(rounds[-1])
    summary = {"env": run.env_name, "seed": run.seed,
               "config": report.to_jsonable(run.config), "rounds": rounds, "final": final,
               "real_episodes": real_episodes,
               "wall_s_this_process": time.perf_counter() - run.t_start}
    out = run.out
    if run.config.video:
        t0 = time.perf_counter()
        summary["video"] = str(_final_video(run))
        summary["video_s"] = time.perf_counter() - t0
    rows = [[r["round"], r["real_steps"], r.get("plan_success"), r.get("sim_success"),
             r.get("q_rank_corr"), r.get("hand_eye_pos_err_mm"), r.get("real_success"),
             r.get("deployed_camera") or "—", r.get("default_camera_success"),
             r.get("camera_steps"),
             {True: "kept", False: "rejected"}.get(r.get("residual_accepted"), "—")]
            for r in rounds]
    report.print_table(f"twinrl run {run.env_name} (seed {run.seed})",
                       ["round", "real steps", "plans solved", "actor sim success", "Q rank",
                        "hand-eye err mm", "real success", "camera", "default camera",
                        "camera steps", "residual"],
                       rows)
    report.write_json(out / "summary.json", summary)
    _plot(out, summary)
    return summary


def _plot(out: Path, summary: dict) -> None:
    """``success.png``: per round, real success with the chosen camera against the fixed
    default camera (evaluation), and the actor's success in the identified twin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rounds = [r for r in summary["rounds"] if r["round"] >= 1]
    if not rounds:
        return
    x = np.arange(len(rounds))
    fig, ax = plt.subplots(figsize=(6, 3.2))
    c = summary["config"]
    n_sim = (c.get("imitation") or {}).get("eval_episodes", 50)
    cams = {r.get("deployed_camera") or c.get("camera") for r in rounds}  # the gate's choice
    cam = cams.pop() if len(cams) == 1 else "deployed"
    for k, (key, label, n) in enumerate((
            ("sim_success", f"actor in the identified twin ({n_sim} episodes)", None),
            ("real_success", f"real, {cam} camera (recorded)", "real_successes"),
            ("default_camera_success", "real, default camera (evaluation)",
             "default_camera_successes"))):
        v = [np.nan if r.get(key) is None else r[key] for r in rounds]
        ax.bar(x + (k - 1) * 0.27, v, 0.27, label=label)
        for i, r in enumerate(rounds):  # the episodes behind each bar
            if n and r.get(n):
                ax.text(x[i] + (k - 1) * 0.27, v[i] + 0.02, f"{int(sum(r[n]))}/{len(r[n])}",
                        ha="center", fontsize=7)
    ax.set_xticks(x, [f"round {r['round']}" for r in rounds])
    ax.set_ylim(0, 1.35)  # room above full bars for their counts and the legend
    ax.set_ylabel("success rate")
    ax.set_title(f"{summary['env']} (seed {summary['seed']}): "
                 f"{summary['real_episodes']} real episodes in all")
    ax.legend(fontsize=7, loc="upper left", ncol=2)
    fig.tight_layout()
    fig.savefig(out / "success.png", dpi=120)
    plt.close(fig)


def _final_video(run: RunContext) -> Path:
    """``final.mp4``: one more episode of the deployed actor on the real twin (not recorded), the
    mount's view from the deployed pose (left: Q's choice, or the default where the gate fell
    back to it) beside a fixed overview of the real scene (right)."""
    from twinrl.envs.system import System
    from twinrl.real.remote import TwinClient
    from twinrl.sim2real.active import DeployConfig

    r = run.config.rounds
    rdir = run.out / f"round{r}"
    env = task_env(run.env_name, run.config, System.load(rdir / "system.json"))
    deployer = _deployer(run, env, rdir, r)
    n = run.twin.width
    twin = _FilmedTwin(TwinClient(run.env_name, seed=run.seed, secret=run.secret,
                                  perturbation=run.perturbation, width=n, height=n))
    camera = deployed_camera(run, r)
    try:
        deployer.run(twin, DeployConfig(camera=camera, episodes=1), seed=90_000 + run.seed)
    finally:
        twin.close()
    view = {"selected": "chosen view", "default": "default view"}.get(camera, f"{camera} view")
    frames = report.label_frames(twin.frames, [view, "real scene"])
    return report.write_video(run.out / "final.mp4", frames, fps=1.0 / env.dt)


class _FilmedTwin:
    """A twin client that keeps, after every step, the mount's frame beside the scene's
    ``overview`` camera (each scaled up 3 times)."""

    def __init__(self, twin):
        self._twin, self.frames = twin, []

    def __getattr__(self, name):
        return getattr(self._twin, name)

    def step(self, action):
        out = self._twin.step(action)
        views = [self._twin.render_images(c, ("rgb",))["rgb"] for c in ("mount", "overview")]
        self.frames.append(np.concatenate([np.repeat(np.repeat(v, 3, 0), 3, 1) for v in views],
                                          1))
        return out

    def close(self):
        self._twin.close()
