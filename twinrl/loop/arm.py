"""The manipulation loop, SAM-RL's (Lv et al., RSS 2023): ``twinrl run --env peg_insertion``
(``needle_threading``, ``spatula_flipping``).

The robot has an arm that acts and a camera on a mount that it can move (``ArmTask.mount``); its
real twin (``twinrl.real.remote.TwinClient``) hides link masses, damping, friction, servo gains,
latency, observation noise, the camera's hand-eye offset and the tool's grasp in the hand. Round 0
records ``K`` episodes of small exciting motions seen from the mount's default pose (or from
several: ``ArmLoopConfig.calibration_poses``), each step's RGB-D + segmentation frame with it.
Every round ``r >= 1`` then runs these stages (``ARM_ROUND``, ``twinrl.loop.Stage`` values, in
``twinrl.loop.arm_stages``, so a killed run resumes at the stage it was in):

1. **calibrate**: the mount camera's hand-eye calibration by visual Real2Sim -- the camera pose
   offset (in the commanded camera's frame) that makes the differentiable renderer's images of
   the recorded states, from each frame's commanded mount pose, match round 0's real frames
   (``twinrl.real2sim.handeye.calibrate_mount``: ``visual.fit_camera`` with a stack of cameras;
   the tool, whose grasp is not known, left out), kept as the identified ``System``'s
   ``"mount"`` camera, so every later render and back-projection of the target uses it; then, with that camera, the tool's grasp
   in the hand (``handeye.fit_grasp``; ``ArmLoopConfig.grasp``: by default on the peg and
   the needle, where it was measured to help), kept as the ``System``'s
   ``System.tool``, so the twin's tool, reward and success sit where the real tool does;
2. **sysid** (``ArmLoopConfig.sysid``): the action latency and the joints' servo gains and
   damping from round 0's transitions (``twinrl.real2sim.sysid``), else the nominal ones;
3. **plan**: trajectory-optimised demonstrations in the identified twin (``twinrl.learn.plans``);
4. **imitation**: the image actor cloned from them (``twinrl.learn.imitation``, demonstrations
   rendered from several mount poses): by default on the target's pose fitted to the mount's
   depth image (``ArmTask.fit_target_pose``, peg and needle) or on the target cloud's
   statistics (spatula);
5. **sensing**: the sensing-aware Q of that actor (``twinrl.learn.sensing``); it gives its
   held-out rank correlation, which the deployment's camera gate reads;
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

The settings are ``ArmLoopConfig`` (``twinrl.loop.arm_config``). Resume, as every family's
(``twinrl.loop.engine``): each stage marks itself done in ``progress.json`` after writing its
outputs; real episodes go to ``dataset/`` as they happen, so a run killed at any moment loses
nothing recorded, and a resumed deployment starts at its first unrecorded episode (episode ``i``
resets with seed ``seed + i``, so the episodes are those an uninterrupted run would have had).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from twinrl import report
from twinrl.loop import arm_report
from twinrl.loop import arm_stages as stages
from twinrl.loop.arm_config import (GRASP_TASKS, NESTED, TASK_IMITATION, ArmLoopConfig,
                                    check_task, grasp_on, imitation_settings, is_arm_task,
                                    make_config, observation, run_env, task_env)
from twinrl.loop.arm_stages import (deployed_camera, deployer, nominal_episodes, record_round0,
                                    round0_poses, sysid_config)
from twinrl.loop.engine import Family, RunContext, Stage
from twinrl.loop.engine import run as run_family
from twinrl.loop.errors import LoopError
from twinrl.loop.rundir import RunDir
from twinrl.real2sim.handeye import calibrate_mount, fit_grasp, tool_geoms

__all__ = ["ArmLoopConfig", "make_config", "run", "ARM_COLLECT", "ARM_ROUND", "FAMILY",
           "is_arm_task", "task_env", "run_env", "grasp_on", "imitation_settings", "observation",
           "deployed_camera", "deployer", "nominal_episodes", "record_round0",
           "round0_poses", "sysid_config", "calibrate_mount", "fit_grasp", "tool_geoms",
           "FilmedTwin", "film_frames",
           "GRASP_TASKS", "TASK_IMITATION", "NESTED", "stages"]

ARM_COLLECT = Stage("collect", needs=(), gives=(), make=stages.collect)
"""Round 0's stage."""

ARM_ROUND = (
    Stage("calibrate", needs=("data",), gives=("camera", "grasp"), make=stages.calibrate,
          load=stages.load_camera, enabled=lambda c: c.calibrate),
    Stage("sysid", needs=("data", "camera", "grasp"), gives=("system", "env"),
          make=stages.identify_system, load=stages.load_system),
    Stage("plan", needs=("env",), gives=(), make=stages.plan),
    Stage("imitation", needs=("env",), gives=(), make=stages.imitate),
    Stage("sensing", needs=("env",), gives=("q_rank",), make=stages.sense,
          load=stages.load_q_rank, enabled=lambda c: c.camera == "selected"),
    Stage("camera_check", needs=("env", "q_rank"), gives=("deploy_camera",),
          make=stages.check_camera, load=stages.load_deploy_camera,
          enabled=lambda c: c.camera == "selected"),
    Stage("residual", needs=("env", "system", "data"), gives=("residual_accepted",),
          make=stages.train_residual, load=stages.load_residual, enabled=lambda c: c.residual),
    Stage("deploy", needs=("env", "deploy_camera", "residual_accepted"), gives=(),
          make=stages.deploy),
)
"""The stages of every round ``r >= 1``, in order."""


# ------------------------------------------------------------------------------ the family
def open_twin(rd: RunDir, env_name: str, config: ArmLoopConfig, seed: int, perturbation, say):
    """The real twin's server at the loop's image size and the dataset writer (its frames too);
    a dataset recorded at another image size is refused in one line."""
    from twinrl.real.dataset import DatasetMismatch, DatasetWriter
    from twinrl.real.remote import TwinClient

    env = task_env(env_name, config)
    n = int(env.config.image_size)
    twin = TwinClient(env_name, seed=seed, secret=rd.secret, perturbation=perturbation, width=n,
                      height=n)
    obs0, _ = twin.reset(seed=seed)
    shapes = {"rgb": (n, n, 3), "depth": (n, n), "segmentation": (n, n)}
    try:
        writer = DatasetWriter(rd.dataset, env=env_name, obs_shape=obs0.shape,
                               action_shape=twin.action_space.shape, obs_dtype=np.float32,
                               action_dtype=np.float32, image_shapes=shapes)
    except ValueError as e:  # a dataset recorded with other shapes (an older twinrl's images)
        twin.close()
        why = (f". This twinrl's {env_name} records {n}x{n} images (ArmConfig.image_size); "
               f"resume with the version that started the run"
               if isinstance(e, DatasetMismatch) and e.key == "image_shapes" else "")
        raise LoopError(f"{e}{why}") from None
    return env, twin, writer, None


RECORD_KEYS = dict.fromkeys(
    ("real_steps", "real_success", "real_successes", "real_return", "camera_steps",
     "chosen_coords", "plan_success", "sim_success", "q_rank_corr", "q_rank_corr_pooled",
     "latency", "residual_accepted", "hybrid_rmse", "hybrid_sim_rmse", "deployed_camera",
     "sim_selected_success", "sim_default_success", "seconds"))
"""A round's row of the summary (from ``progress.json``; evaluation's merged in after)."""


def summarise(run: RunContext, summary: dict) -> None:
    """The real episodes the run used in all."""
    summary["real_episodes"] = run.K * (run.config.rounds + 1)


def write_outputs(run: RunContext, summary: dict) -> None:
    """The table, the last round's figures (``ArmLoopConfig.figures``: ``sense/``, named in the
    summary's ``figures``), ``summary.json``, ``success.png`` and ``report.md``."""
    rows = [[r["round"], r["real_steps"], r.get("plan_success"), r.get("sim_success"),
             r.get("q_rank_corr"), r.get("hand_eye_pos_err_mm"), r.get("real_success"),
             r.get("deployed_camera") or "—", r.get("default_camera_success"),
             r.get("camera_steps"),
             {True: "kept", False: "rejected"}.get(r.get("residual_accepted"), "—")]
            for r in summary["rounds"]]
    report.print_table(f"twinrl run {run.env_name} (seed {run.seed})",
                       ["round", "real steps", "plans solved", "actor sim success", "Q rank",
                        "hand-eye err mm", "real success", "camera", "default camera",
                        "camera steps", "residual"],
                       rows)
    if run.config.figures:
        t0 = time.perf_counter()
        env = stages.load_system(run, run.dir.round(run.config.rounds))["env"]
        summary["figures"] = arm_report.write_figures(run, env, summary["rounds"][-1])
        summary["figures_s"] = time.perf_counter() - t0
    report.write_json(run.dir.summary, summary)
    plot_success(run.dir.success_plot, summary)
    arm_report.write_report(run.dir.out, summary)


def final_video(run: RunContext, values: dict) -> Path:
    """``final.mp4``: one more episode of the deployed actor on the real twin (not recorded), each
    frame the real scene (the fixed ``overview`` camera, left) beside the mount's view from the
    deployed pose (right: Q's choice, or the default where the gate fell back to it), the image
    the actor acts on, labelled with the task and captioned with the step and the mount's pose
    (``film_frames``), from the camera's move at the start to a last frame held a second with
    the real verdict."""
    from twinrl.real.remote import TwinClient
    from twinrl.sim2real.active import DeployConfig

    rdir = run.dir.round(run.config.rounds)
    env = values["env"]
    dep = deployer(run.config, env, rdir, values["residual_accepted"])
    n = run.twin.width
    twin = FilmedTwin(TwinClient(run.env_name, seed=run.seed, secret=run.secret,
                                 perturbation=run.perturbation, width=n, height=n))
    camera = values["deploy_camera"] or run.config.camera
    try:
        res = dep.run(twin, DeployConfig(camera=camera, episodes=1), seed=90_000 + run.seed)
    finally:
        twin.close()
    view = {"selected": "chosen view", "default": "default view"}.get(camera, f"{camera} view")
    frames = film_frames(twin.shots, env, run.env_name, view, env.episode_length,
                         n * max(2, -(-256 // n)), verdict=bool(res["success"][0]),
                         hold=max(1, round(1.0 / env.dt)))
    return report.write_video(run.dir.video, frames, fps=1.0 / env.dt)


def film_frames(shots, env, task: str, view: str, T: int, height: int,
                verdict: bool | None = None, hold: int = 1) -> list[np.ndarray]:
    """``final.mp4``'s frames of ``FilmedTwin.shots``: per shot ``report.compose_frame`` of the
    real scene (left, labelled with the ``task``) and the mount's ``view`` (right, the image the
    actor acts on), both scaled to ``height``, captioned with the step of ``T`` and the mount's
    pose (``env.mount``'s azimuth, elevation and distance); the last frame repeated ``hold``
    times with ``verdict`` (the real twin's success) when given."""
    labels = [f"real scene: {task}", f"{view}: the actor's image"]
    frames, when = [], ""
    for shot in shots:
        when = caption = ("camera moved, before acting" if shot["t"] == 0 else
                          f"step {shot['t']}/{T}")
        if shot.get("coords") is not None:
            az, el, dist = np.asarray(env.mount.spherical(
                np.asarray(shot["coords"], np.float32)), float)
            caption += (f"  |  {view} at azimuth {np.degrees(az):.0f}\u00b0, elevation "
                        f"{np.degrees(el):.0f}\u00b0, {dist:.2f} m")
        frames.append(report.compose_frame([shot["scene"], shot["view"]], labels, caption,
                                           height=height))
    if frames and verdict is not None:
        last = shots[-1]
        end = report.compose_frame([last["scene"], last["view"]], labels,
                                   f"real twin: {'success' if verdict else 'failure'}  |  "
                                   f"{when}", height=height)
        frames += [end] * int(hold)
    return frames


def _family() -> Family:
    """The SAM-RL family, with the stages ``ARM_COLLECT`` and ``ARM_ROUND`` hold when called
    (a test may replace them)."""
    return Family("manipulation", ArmLoopConfig, ARM_COLLECT, ARM_ROUND, check_task, open_twin,
                  RECORD_KEYS, summarise, final_video, write_outputs)


FAMILY = _family()
"""The SAM-RL family: what it supplies to ``twinrl.loop.engine``."""


def run(env_name: str, out: str | Path, config: ArmLoopConfig = ArmLoopConfig(), *,
        seed: int = 0, resume: bool = False, progress: bool = True,
        perturbation=None) -> dict[str, Any]:
    """Run the manipulation loop on ``env_name``'s real twin (hidden perturbation drawn from
    ``seed``) into ``out``; returns the summary (also ``out/summary.json``)."""
    if not is_arm_task(env_name):
        raise LoopError(f"{env_name!r} is not a manipulation task (twinrl.loop runs it)")
    return run_family(_family(), env_name, out, config, seed=seed, resume=resume,
                      progress=progress, perturbation=perturbation)


def plot_success(path: Path, summary: dict) -> None:
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
    fig.savefig(path, dpi=120)
    plt.close(fig)


class FilmedTwin:
    """A twin client that films while ``film`` is true: after every camera move and every step,
    a shot ``{"view": the mount's RGB frame (what an image actor sees), "scene": the scene's
    ``overview`` camera, "coords": the mount's commanded pose, "t": the steps since the reset}``
    (``shots``); ``frames``: each shot's view beside its scene, each scaled up 3 times."""

    def __init__(self, twin, film: bool = True):
        self._twin, self.shots, self.film, self._t = twin, [], film, 0

    def __getattr__(self, name):
        return getattr(self._twin, name)

    @property
    def frames(self) -> list[np.ndarray]:
        """The shots' view and scene side by side, each scaled up 3 times."""
        return [np.concatenate([np.repeat(np.repeat(s[k], 3, 0), 3, 1)
                                for k in ("view", "scene")], 1) for s in self.shots]

    def _shoot(self) -> None:
        views = [self._twin.render_images(c, ("rgb",))["rgb"] for c in ("mount", "overview")]
        coords = self._twin.mount_coords
        self.shots.append({"view": views[0], "scene": views[1], "t": self._t,
                           "coords": None if coords is None else np.asarray(coords, np.float64)})

    def reset(self, *args, **kwargs):
        self._t = 0
        return self._twin.reset(*args, **kwargs)

    def move_camera(self, coords) -> int:
        steps = self._twin.move_camera(coords)
        if self.film:
            self._shoot()
        return steps

    def step(self, action):
        out = self._twin.step(action)
        self._t += 1
        if self.film:
            self._shoot()
        return out

    def close(self):
        self._twin.close()
