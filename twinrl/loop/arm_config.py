"""The SAM-RL loop's settings (``ArmLoopConfig``, ``make_config``: ``twinrl run --set``) and the
task as the loop runs it (``task_env``, ``run_env``), with the checks of both."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Mapping

from twinrl.loop.errors import LoopError
from twinrl.loop.rundir import RunDir

__all__ = ["ArmLoopConfig", "make_config", "is_arm_task", "task_env", "run_env", "grasp_on",
           "imitation_settings", "observation", "check_task", "GRASP_TASKS", "TASK_IMITATION",
           "STAGE_IMITATION", "NESTED"]


def _imitation_defaults() -> dict[str, Any]:
    # demonstrations seen from 8 mount poses each; the observation and the DAgger rounds are the
    # task's (observation, TASK_IMITATION), unless set. 16 poses gave no more: needle twin 0's
    # identified twin, 46 demonstrations, 50 fresh starts from random views: 68 % with 8, 70 %
    # with 16 (68 % fitted 20,000 steps); only 60 % of the random views' steps give a pose
    # estimate within 5 mm (``plans.accurate``): the views limit the pose actor, not its data
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


STAGE_IMITATION: dict[str, Any] = {"dagger_rounds": 0, "restarts": 3}
"""The imitation stage's settings on every task, under ``TASK_IMITATION`` and ``--set
imitation.FIELD=...``. ``restarts``: three clonings, the best on the stage's 20 eval starts
going on; one cloning varies with its keys far more than with its data (peg twin 1's identified
twin, the stage's own seed, 50 other starts: 78 % alone, 92 % the best of three; two other
seeds alone 94 and 50 %), for 2-3x the cloning's time (195 -> 425 s there, on shared cores).
Kept out of ``ArmLoopConfig.imitation`` so that runs from before it resume as they are."""


def imitation_settings(config: ArmLoopConfig, env) -> dict[str, Any]:
    """The imitation stage's settings on ``env``: ``STAGE_IMITATION`` and the task's
    (``TASK_IMITATION``, the observation) under the loop's ``imitation`` settings."""
    return {**STAGE_IMITATION, **TASK_IMITATION.get(env.name, {}), **dict(config.imitation),
            "observation": observation(env, config.imitation)}


def observation(env, imitation: Mapping[str, Any]) -> str:
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
    calibration_frames: int = 30
    """Round-0 frames the calibration and the grasp's fit use, evenly spread. 30 instead of 10
    fits the needle's grasp three times closer (its tool point 0.82 / 1.12 mm from the hidden
    one on twins 0 / 1, against 2.67 / 3.42 mm: ``bench/hand_eye.py --frames 30 --grasp``; the
    hand-eye offset stays within 0.2-0.4 mm), where the fitted grasp made the twin wrong (needle
    twin 0: 6 of the actor's 8 real failures thread in the twin at the fitted grasp, 2 at the
    hidden one: ``bench/real_failures.py``). Needle twins 0 / 1's loops then solve 100 / 94 % of
    50 real starts with Q's camera (84 / 88 % with 10 frames), for ~2 more minutes of the
    stage."""
    calibration_steps: int = 40
    """Adam steps of the calibration and of the grasp's fit (``VisualConfig.steps``), before
    their Levenberg-Marquardt refinement, which settles the result: 40 steps and 150 gave the
    same hand-eye offset (within 0.01 mm / 0.001 deg) and the same tool point (within 0.02 mm)
    on peg and needle twins 0-1, in 43-83 s a fit against 131-194 s (``bench/hand_eye.py
    --steps 40 150 --grasp``, 2 shared cores). Rendering the frames, not compiling, is the
    stage's time (~0.6-0.9 s a step on shared cores)."""
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
    ``System.tool`` (``ArmTask.set_grasp``): the twin's tool, its reward and its
    success then sit where the real tool does. Needs ``calibrate``. ``None`` (the default): on for
    the tasks where it was measured to help (``GRASP_TASKS``), off elsewhere. Spatula: the
    tool point 2.40 / 2.05 / 2.09 mm off on twins 0-2 against 4.56 / 13.14 / 10.95 nominal;
    twin 1's loop with it (and four DAgger rounds) 64 / 66 % on 50 real starts with the chosen /
    default camera, where with the nominal grasp 0/5 and 0/10; twin 2's loop with it solves
    45 of 48 plans (and twin 1's loop 5/5 and 9/10) with the controller calibrated
    (``calibrate_controller``), 0 of 48 without. The tool point against the truth
    (``bench/hand_eye.py --grasp``): needle twins 0-2 0.8-3.4 mm (nominal: 8.70 / 4.36 / 2.10),
    peg twins 0-2 0.66 / 1.13 / 0.77 mm (nominal: 5.78 / 12.21 / 10.61).
    Peg twins 1 and 2, 50 real starts: 88 and 80 % with the chosen camera (twin 1's loop with the
    nominal grasp: 2/5 chosen, 5/10 default)."""
    sysid: bool = True
    """Identify the action latency and the arm's servo dynamics (joint gains and damping) from
    round 0's transitions (``arm_stages.sysid_config``; 4 min on 2 cores). On needle twin 2 the
    twin's hidden latency, gains, damping and noise cost the chosen camera 24 points from sim to
    real (94 -> 70 %); identified (latency right, gains within 0.5-16 %), 90 -> 84 %. The masses
    are left nominal: the servo-tracked motions barely show them (fitted, link 2's came out
    7x its truth there)."""
    calibrate_controller: bool = True
    """Calibrate the Cartesian controller to the identified servos (``ArmTask.servo_speed``,
    kept as the ``System.controller``) in the identified twin and on the real
    arm (``RealTwin.calibrate_controller``, set by the deployment) from round 1 on; round 0
    records with the nominal controller, and sysid and the hybrid model fit round 0's episodes
    under it. The controller sets targets a step from the measured joints, so each joint moves
    at its servo's gain over damping: a twin's +-15 % servos bend the commanded motion (spatula
    twin 2: a lift 31 degrees off, 74 % as far) and its plans fail even with the true parameters
    (0/8); calibrated with the true speeds 8/8, with the identified ones 6/8."""
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
    camera_min_rank: float = 0.35
    """``"selected"`` deploys Q's choice only if Q's rank correlation on its held-out states
    (the sensing stage's ``rank_corr``) reaches this; below it the round deploys the default
    camera and says so (``deployed_camera``). On 50 real starts per twin (``bench/sensing.py
    --run``), every Q below 0.35 chose worse than the default camera: peg 0.27 -12 points, 0.31
    -6, 0.33 -2; spatula twin 2's -0.12 -20 (76 against 96 %), twin 0's 0.02 -6; every Q from
    0.38 chose as well or better: spatula twin 1 +0, needle 0.41 / 0.50 / 0.63 +22 / +16 / +26
    (twins 1 / 0 / 2). It was 0.2, before the peg's three runs. The held-out rank is no
    sure guide: spatula twin 0's Q at 0.37 passes and cost 42 points (50 against 92 %); on the
    peg and the spatula the default view does as well as a random one, so a choice there can
    only lose (``docs/known-limits.md``); ``camera_check`` catches what the rank passes."""
    camera_check: int = 20
    """Where Q's rank passes ``camera_min_rank``, ``"selected"`` deploys Q's choice only if, on
    this many fresh starts in the identified twin, the image actor succeeds more often with it
    than with the default camera (``twinrl.learn.camera_choice.check_choice``; no real episode);
    0: the rank gate alone. In simulation on 50 starts, the identified twin gave the sign of the
    real difference on each run tried: spatula twin 0 58 against 98 % (real 50 against 92 %),
    peg twins 0 / 1 92 against 96 and 80 against 90 % (real -6, -12), needle twin 1 82 against
    58 % (real 86 against 64 %)."""
    eval_episodes: int = 10
    """Evaluation-only real episodes (not recorded) of the deployed actor with the default
    camera; 0: none."""
    residual: bool = True
    """Train a residual policy on the actor through the hybrid model and deploy it if
    ``residual.accept`` accepts it (the ``residual`` stage; ``"pose"`` actors only: for others the
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
    """Write final.mp4: a deployment episode, the real scene beside the deployed view (the image
    the actor acts on)."""
    figures: bool = True
    """Draw the last round's figures for ``report.md`` in ``OUT/sense/``
    (``twinrl.loop.arm_report.write_figures``), for the start of its last deployed episode and
    the pose the deployment chose there: Q's landscape over the mount's workspace with the
    default and chosen views and the actor's saliency on each; without a Q, the saliency on the
    deployed view. One small compilation, no ascent: on the needle 36 s of CPU (about a
    minute on 2 cores shared with other jobs), where ``twinrl sense``'s ascent, landscape and
    saliency took 155 s of CPU (4 min)."""
    image_size: int | None = None
    """Width and height (pixels) of the mount camera's images, recorded, simulated and deployed;
    ``None``: the task's (``ArmConfig.image_size``). The needle at 128 instead of its 64: the
    image actor 74-86 % from random views where 64 gave 50-75 %, and the default camera then
    solves 88-100 % of real starts (measured on needle twins 0 and 1)."""

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
        if isinstance(self.camera_check, bool) or not isinstance(self.camera_check, int) \
                or self.camera_check < 0:
            raise LoopError(f"camera_check must be an integer >= 0 (fresh starts in the "
                            f"identified twin; 0: none), got {self.camera_check!r}")
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
    saved = json.loads(RunDir(run_dir).settings.read_text())
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
    from twinrl.envs.arm.task import ArmTask

    return issubclass(envs.registry.TASKS[env_name].env_class, ArmTask)




def check_task(env_name: str, config: ArmLoopConfig) -> None:
    """The SAM-RL family runs the manipulation tasks (``is_arm_task``)."""
    if not is_arm_task(env_name):
        raise LoopError(f"{env_name!r} is not a manipulation task (twinrl.loop runs it)")
