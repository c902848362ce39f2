"""The SAM-RL loop's stages (``twinrl.loop.arm``): round 0's recording, then per round the
hand-eye calibration, sysid, planning, imitation, the sensing-aware Q, the residual policy and
the deployment. Each stage returns the values it gives, saves what it computed under its round's
directory and marks itself done; its ``load`` reads those values back on ``--resume``."""

from __future__ import annotations

import json
import time
from typing import Any

import numpy as np

from twinrl import eval as evaluation
from twinrl import report
from twinrl.envs.system import ControllerCalibration, ToolGrasp
from twinrl.loop.arm_config import grasp_on, imitation_settings, task_env
from twinrl.loop.engine import RunContext, real_steps, seconds_so_far
from twinrl.loop.rundir import RoundDir
from twinrl.loop.shared import EpisodeLog, collect_round0

__all__ = ["collect", "record_round0", "round0_poses", "calibrate", "load_camera",
           "identify_system", "load_system", "nominal_episodes", "sysid_config",
           "plan", "imitate", "sense", "load_q_rank", "train_residual", "load_residual",
           "deployer", "deployed_camera", "check_camera", "sim_camera_check", "load_deploy_camera",
           "deploy"]


# ------------------------------------------------------------------------------ round 0
def collect(run: RunContext, r: int, rdir: RoundDir) -> None:
    """Round 0: ``K`` episodes of exciting motions (``record_round0``), recorded with every
    step's frame (those the dataset already holds are not recorded again)."""
    def episodes(todo):
        return {"camera_steps": record_round0(run.twin, run.writer, run.nominal_env, run.seed,
                                              round0_poses(run), todo)}

    collect_round0(run, "exciting episodes with images", episodes)


def record_round0(twin, writer, env, seed: int, poses, episodes) -> int:
    """The loop's round-0 episodes ``episodes`` on ``twin`` (reset with seed ``seed + e``, the
    exciting motions ``sysid.excitation_actions`` draws for ``[seed, e]``), episode ``e`` seen
    from the mount at ``poses[e]``, recorded with every step's frame by ``writer``; the mount
    goes back to its default pose at the end. Returns the camera moves' steps."""
    from twinrl.real.record import record_episodes
    from twinrl.real2sim import sysid

    T, steps = env.episode_length, [0]

    def policy(e):
        acts = sysid.excitation_actions(np.random.default_rng([seed, e]), T, env.action_size)
        return lambda o, t: acts[min(t, T - 1)]

    def move(e):
        steps[0] += int(twin.move_camera(poses[e]))

    record_episodes(twin, episodes, policy, lambda e: seed + e, writer=writer, images=True,
                    after_reset=move)
    return steps[0] + int(twin.move_camera(env.mount.default))


def round0_poses(run: RunContext) -> np.ndarray:
    """The mount pose (unconstrained coordinates) of each round-0 episode: the
    ``calibration_poses`` poses in turn."""
    poses = run.nominal_env.mount.calibration_poses(run.config.calibration_poses)
    return poses[np.arange(run.K) % len(poses)]


# ------------------------------------------------------------------------------ calibrate
def calibrate(run: RunContext, r: int, rdir: RoundDir, data) -> dict[str, Any]:
    """Hand-eye calibration from round 0's frames, each seen from its episode's mount pose ->
    ``calibration.json`` (the fitted offset, and the camera it gives at the default pose), and
    the tool's grasp where ``grasp_on``."""
    from twinrl.real2sim import visual
    from twinrl.real2sim.handeye import calibrate_mount, fit_grasp

    env = run.nominal_env
    frames = visual.frames_from_dataset(run.env_name, data, run.config.calibration_frames,
                                        episodes=range(run.K))
    poses = round0_poses(run)[[f["episode"] for f in frames]]
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
    report.write_json(rdir.calibration, {
        "camera": {"pos": np.asarray(cam.pos), "quat": np.asarray(cam.quat),
                   "fovy": np.asarray(cam.fovy), "width": W, "height": H},
        "pos_offset": mount.pos_offset, "rot_offset": mount.rot_offset, "frames": len(frames),
        "poses": len(np.unique(poses, axis=0)),
        "loss": min(x["final_loss"] for x in info["runs"]), "grasp": grasp})
    run.ev.mark(f"round{r}/calibrate", **evaluation.hand_eye_errors(
        run.env_name, run.seed, mount, run.perturbation, run.secret), **errors)
    run.prog.mark(f"round{r}/calibrate",
                  seconds=seconds_so_far(run.prog, r, calibrate=time.perf_counter() - t0))
    return load_camera(run, rdir)  # as a resumed run reads them: float64 from the JSON


def load_camera(run: RunContext, rdir: RoundDir, **_) -> dict[str, Any]:
    """The calibrated mount camera and the grasp, from ``calibration.json``."""
    from twinrl.render import Camera

    f = rdir.calibration
    if not run.config.calibrate or not f.exists():
        return {"camera": None, "grasp": None}
    doc = json.loads(f.read_text())
    c = doc["camera"]
    return {"camera": Camera(np.asarray(c["pos"]), np.asarray(c["quat"]),
                             np.asarray(c["fovy"]), int(c["width"]), int(c["height"])),
            "grasp": doc.get("grasp")}


# ------------------------------------------------------------------------------ sysid
def identify_system(run: RunContext, r: int, rdir: RoundDir, data, camera,
                    grasp=None) -> dict[str, Any]:
    """The identified ``System`` -> ``system.json``: sysid's parameters and latency (or the
    nominal ones) with the calibrated mount camera and the tool's identified grasp."""
    from twinrl.envs.system import System

    t0 = time.perf_counter()
    system = System.nominal(run.env_name)
    if run.config.sysid:
        from twinrl.real2sim import sysid

        fitted = nominal_episodes(run, data)
        run.say(f"  sysid on {len(fitted)} real transitions ...")
        res = sysid.fit(run.nominal_env, fitted, sysid_config())
        system = res.system
        run.ev.mark(f"round{r}/sysid", **evaluation.sysid_errors(
            run.nominal_env, res, run.env_name, run.seed, run.perturbation, run.secret))
    if camera is not None:
        system = system.replace(cameras={"mount": camera})
    if grasp is not None:
        system = system.replace(tool=ToolGrasp(np.asarray(grasp["pos_offset"], np.float64),
                                               np.asarray(grasp["rot_offset"], np.float64)))
    if run.config.sysid and run.config.calibrate_controller:
        system = system.replace(controller=ControllerCalibration(
            run.nominal_env.servo_speed(system.params)))
    system.save(rdir.system)
    run.prog.mark(f"round{r}/sysid", latency=system.latency,
                  seconds=seconds_so_far(run.prog, r, sysid=time.perf_counter() - t0))
    return load_system(run, rdir)


def load_system(run: RunContext, rdir: RoundDir, **_) -> dict[str, Any]:
    """The identified ``System`` and the task built on it (what every later stage simulates)."""
    system = rdir.identified_system(run.env_name)
    return {"system": system, "env": task_env(run.env_name, run.config, system)}


def nominal_episodes(run: RunContext, data):
    """The real episodes recorded with the nominal controller, which the fits of real
    transitions (sysid, the hybrid model) simulate them with: all of them, or, with the
    controller calibrated from round 1 on (``ArmLoopConfig.calibrate_controller``), round 0's."""
    if run.config.sysid and run.config.calibrate_controller:
        return data.first_episodes(run.K)
    return data


def sysid_config():
    """The arm's sysid: latency 0-1 and the 7 joints' servo gains and damping (what the
    exciting motions show; ``panda.xml`` names joints and servos ``joint1``..``joint7``);
    15 Levenberg-Marquardt steps per latency (it had converged by 10 on needle twin 2), no
    bound tests (damping is far from 0). Windows start from the recorded states: the joints
    are measured to 2 mrad, and on spatula twin 0 the parameters come within 0.7-18 % of the
    truth in 166 s. Estimating every window's start as well (31 numbers a window there; the
    pancake's unseen spin is held by the starts' prior) gives 0.3-17 %, far slower.

    The parameters' prior stays sysid's weak default (3). The data pin the gains loosely: on
    spatula twin 2 their sd from 300 transitions is 13-39 % and the fit lands 17-44 % off
    there, gain and damping of a joint off by about one factor (joint 1: 0.75 and 0.76): the
    controller's targets are the measured joints plus a step, so a joint's speed shows its
    gain over its damping, their common scale only through gravity and inertia. A datasheet
    prior (``prior_sd=0.2``) bounds that (18 % there, 21 % on twin 1 against 29 %) but costs
    where the data do speak (needle twin 2: largest error 9.4 -> 13.4 %, median 3.2 -> 5.8 %),
    and twin 2's plans failed with the true parameters as well until the controller was
    calibrated to the servo speeds, which the data do pin; ``bench/arm_sysid.py --prior-sd``
    measures it."""
    from twinrl.envs.arm.kinematics import N_JOINTS
    from twinrl.real2sim import sysid

    names = tuple(f"{f}/joint{i}" for f in ("damping", "gain") for i in range(1, N_JOINTS + 1))
    return sysid.SysidConfig(params=names, lm_steps=15, bound_lr=0.0, estimate_start=False)




# ------------------------------------------------------------------------------ learn in the twin
def plan(run: RunContext, r: int, rdir: RoundDir, env) -> None:
    """Trajectory-optimised demonstrations in the identified twin -> ``plans.npz``."""
    from twinrl.learn import plans

    c = run.config
    run.say(f"  planning {c.demonstrations} demonstrations in the identified twin ...")
    t0 = time.perf_counter()
    res = plans.plan(env, c.demonstrations, c.trajopt_iterations, min(10, c.demonstrations),
                     run.seed + r, restarts=c.trajopt_restarts)
    plans.save(rdir.plans, res)
    solved = int(np.sum(np.asarray(res["success"])))
    if solved < 0.25 * c.demonstrations:  # the actor learns from these alone
        run.say(f"  [yellow]only {solved} of {c.demonstrations} plans solved the task in the "
                f"identified twin[/] (trajopt_iterations={c.trajopt_iterations}, "
                f"trajopt_restarts={c.trajopt_restarts})")
    run.prog.mark(f"round{r}/plan", plan_success=res["success_rate"],
                  seconds=seconds_so_far(run.prog, r, plan=time.perf_counter() - t0))


def imitate(run: RunContext, r: int, rdir: RoundDir, env) -> None:
    """The image actor cloned from the demonstrations -> ``actor/``."""
    from twinrl.learn.runner import continue_run

    run.say("  cloning the image actor ...")
    t0 = time.perf_counter()
    overrides = {**imitation_settings(run.config, env), "demonstrations": str(rdir.plans)}
    s = continue_run(run.env_name, "imitation", rdir.actor, seed=run.seed + r,
                     overrides=overrides, progress=run.progress, env=env)
    run.prog.mark(f"round{r}/imitation", sim_success=s["final"].get("success"),
                  seconds=seconds_so_far(run.prog, r, imitation=time.perf_counter() - t0))


def sense(run: RunContext, r: int, rdir: RoundDir, env) -> dict[str, Any]:
    """The sensing-aware Q of the actor -> ``q/``. Gives ``q_rank``: Q's rank correlation on its
    held-out states (what the deployment's camera gate reads)."""
    from twinrl.learn.runner import continue_run

    run.say("  learning the sensing-aware Q ...")
    t0 = time.perf_counter()
    overrides = {**dict(run.config.sensing), "actor": str(rdir.actor)}
    s = continue_run(run.env_name, "sensing", rdir.q, seed=run.seed + r,
                     overrides=overrides, progress=run.progress, env=env)
    run.prog.mark(f"round{r}/sensing", q_rank_corr=s["final"].get("rank_corr"),
                  q_rank_corr_pooled=s["final"].get("rank_corr_pooled"),
                  seconds=seconds_so_far(run.prog, r, sensing=time.perf_counter() - t0))
    return load_q_rank(run, rdir)


def load_q_rank(run: RunContext, rdir: RoundDir, **_) -> dict[str, Any]:
    """Q's held-out rank correlation, from its training's ``q/summary.json``."""
    f = rdir.q_summary
    final = json.loads(f.read_text()).get("final", {}) if f.exists() else {}
    return {"q_rank": final.get("rank_corr")}


# ------------------------------------------------------------------------------ residual
def train_residual(run: RunContext, r: int, rdir: RoundDir, env, system,
                   data) -> dict[str, Any]:
    """The hybrid model (``hybrid/``) and the residual policy through it (``residual/``: the
    trained one if ``residual.accept`` keeps it, else all zeros, exactly the actor). Gives
    ``residual_accepted``: the gate's verdict, None where no residual was trained."""
    import jax

    from twinrl.learn.checkpoint import save_policy
    from twinrl.learn.sensing import load_actor
    from twinrl.sim2real import active, hybrid, residual

    t0 = time.perf_counter()
    actor, actor_params, _ = load_actor(rdir.actor)
    if set(actor.obs_spec) != {"estimate"}:
        run.say(f"  no residual policy: the actor reads {', '.join(sorted(actor.obs_spec))}, "
                f"which the hybrid model cannot render (a 'pose' actor can have one)")
        run.prog.mark(f"round{r}/residual", residual_accepted=None)
        return {"residual_accepted": None}
    seed = run.seed + r
    # the transitions under the controller that recorded them; the model's correction then
    # rides on the calibrated twin (``make_dynamics``)
    fitted = nominal_episodes(run, data)
    run.say(f"  fitting the hybrid dynamics to {len(fitted)} real transitions ...")
    fit = hybrid.fit(env.with_system(system.replace(controller=None)), fitted, latency=system.latency,
                     rng=jax.random.key(seed))
    hybrid.save(rdir.hybrid, fit)
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
        return {"residual_accepted": None}
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
    save_policy(rdir.residual, pol.delta, params, kind="residual", metrics=metrics)
    run.prog.mark(f"round{r}/residual", residual_accepted=v.accepted, **errors,
                  residual_model_return=[v.before, v.after],
                  residual_sim_return=[v.reference_before, v.reference_after],
                  seconds=seconds_so_far(run.prog, r, residual=time.perf_counter() - t0))
    return {"residual_accepted": bool(v.accepted)}


def load_residual(run: RunContext, rdir: RoundDir, **_) -> dict[str, Any]:
    """The gate's verdict as the residual's checkpoint recorded it (None: none trained)."""
    m = rdir.residual_metrics()
    return {"residual_accepted": None if m is None or "accepted" not in m
            else bool(m["accepted"])}


# ------------------------------------------------------------------------------ deploy
def deployer(config, env, rdir: RoundDir, residual_accepted: bool | None):
    """The round's ``Deployer``: its actor, its Q (camera ``"selected"``) and, when the round's
    residual was accepted (``residual_accepted``), that residual."""
    from twinrl.learn.sensing import SensingConfig, load_actor
    from twinrl.sense import load_q
    from twinrl.sim2real.active import Deployer, residual_correction

    actor, actor_params, _ = load_actor(rdir.actor)
    q = q_params = sensing = correction = None
    if config.camera == "selected":
        q, q_params, meta = load_q(rdir.q)
        sensing = SensingConfig.from_dict(meta.get("config") or {})
    if residual_accepted:
        from twinrl.learn.checkpoint import load_policy

        delta, params, _ = load_policy(rdir.residual)
        correction = residual_correction(delta, params)
    return Deployer(env, actor, actor_params, q=q, q_params=q_params, sensing=sensing,
                    residual=correction)


def deployed_camera(config, q_rank: float | None) -> str:
    """The deployment's camera: ``config.camera``, except ``"selected"`` falls back to
    ``"default"`` where Q ranked its held-out states (``q_rank``) below ``camera_min_rank`` (or
    was not scored)."""
    if config.camera != "selected":
        return config.camera
    ok = q_rank is not None and np.isfinite(q_rank) and q_rank >= config.camera_min_rank
    return "selected" if ok else "default"


def check_camera(run: RunContext, r: int, rdir: RoundDir, env, q_rank) -> dict[str, Any]:
    """The deployment's camera -> ``camera_check.json``: Q's choice where Q's held-out rank
    reaches ``camera_min_rank`` (``deployed_camera``) and, on ``camera_check`` fresh starts in the
    identified twin, the actor succeeds more often with Q's choice than with the default camera
    (``check_choice``); else the default camera. Gives ``deploy_camera``."""
    config, t0 = run.config, time.perf_counter()
    doc: dict[str, Any] = {"q_rank": q_rank, "camera_min_rank": config.camera_min_rank,
                           "camera_check": config.camera_check}
    camera = deployed_camera(config, q_rank)
    if camera != "selected":
        rank = "not scored" if q_rank is None else f"{q_rank:.2f}"
        run.say(f"  [yellow]deploying the default camera[/]: Q's rank correlation on its "
                f"held-out states ({rank}) is below camera_min_rank {config.camera_min_rank:g}")
        doc.update(camera=camera, reason="rank")
    elif config.camera_check:
        chk = sim_camera_check(run, r, rdir, env)
        camera = "selected" if chk.pays else "default"
        doc.update(chk.as_dict(), camera=camera, reason="identified twin")
        n = config.camera_check
        verdict = ("deploying Q's choice" if chk.pays else
                   "[yellow]deploying the default camera[/]: Q's choice does not pay there")
        run.say(f"  in the identified twin, Q's camera succeeds on {int(chk.selected.sum())}/{n} "
                f"starts, the default camera on {int(chk.default.sum())}/{n}: {verdict}")
    else:
        doc.update(camera=camera, reason="rank")
    report.write_json(rdir.camera_check, doc)
    run.prog.mark(f"round{r}/camera_check", deploy_camera=camera,
                  sim_selected_success=doc.get("selected_success"),
                  sim_default_success=doc.get("default_success"),
                  seconds=seconds_so_far(run.prog, r, camera_check=time.perf_counter() - t0))
    return {"deploy_camera": camera}


def sim_camera_check(run: RunContext, r: int, rdir: RoundDir, env):
    """``check_choice`` of the round's actor and Q on ``camera_check`` fresh starts of ``env``
    (keys of their own: no start the actor or Q trained on), with a line every few choices."""
    import jax

    from twinrl.learn.camera_choice import check_choice

    dep = deployer(run.config, env, rdir, False)
    n = run.config.camera_check
    keys = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(run.seed + r), 0xCA3), n)
    run.say(f"  checking Q's camera choice against the default camera on {n} starts in the "
            f"identified twin ...")
    t0, every = time.perf_counter(), max(1, n // 4)

    def tick(i):
        if (i + 1) % every == 0 and i + 1 < n:
            run.say(f"    {i + 1}/{n} choices ({time.perf_counter() - t0:.0f} s)")
    return check_choice(env, dep.q, dep.q_params, dep.actor, dep.actor_params, dep.sensing, keys,
                        on_choice=tick)


def load_deploy_camera(run: RunContext, rdir: RoundDir, **_) -> dict[str, Any]:
    """The camera ``check_camera`` chose, from ``camera_check.json``."""
    return {"deploy_camera": json.loads(rdir.camera_check.read_text())["camera"]}


def deploy(run: RunContext, r: int, rdir: RoundDir, env, deploy_camera,
           residual_accepted) -> None:
    """``K`` real episodes of the image actor with the chosen camera, recorded as they happen
    (a resumed deployment starts at its first unrecorded episode: episode ``i`` resets with
    seed ``1000 r + seed + i``); then, evaluation only, the same actor with the fixed default
    camera on ``eval_episodes`` unrecorded episodes."""
    from twinrl.sim2real.active import DeployConfig

    prog, K, config = run.prog, run.K, run.config
    t0 = time.perf_counter()
    dep = deployer(config, env, rdir, residual_accepted)
    log = EpisodeLog(run, r, "deploy_partial")
    rows, have = log.rows, len(log)
    camera = deploy_camera or config.camera  # None: the check stage is off (not "selected")
    run.say(f"  deploying on the real twin ({K - have} episodes, camera {camera}) ...")
    cfg = DeployConfig(camera=camera, episodes=K)

    dep.run(run.twin, cfg, seed=1000 * r + run.seed, start=have, writer=run.writer,
            on_episode=log.add)
    t_eval = time.perf_counter()
    if config.eval_episodes:
        base = evaluation.deployed_success(
            run.env_name, run.seed, dep, DeployConfig(camera="default",
                                                      episodes=config.eval_episodes),
            run.perturbation, run.secret, size=run.twin.width)
        run.ev.mark(f"round{r}/deploy", default_camera_success=base["success_rate"],
                    default_camera_successes=base["success"])
        if dep.residual is not None:  # what the residual changed, on the same episodes
            cfg = DeployConfig(camera=camera, episodes=config.eval_episodes)
            rows_eval = {name: evaluation.deployed_success(
                run.env_name, run.seed, d, cfg, run.perturbation, run.secret,
                size=run.twin.width)["success"]
                for name, d in (("with", dep),
                                ("without", deployer(config, env, rdir, False)))}
            run.ev.mark(f"round{r}/deploy", residual_eval_successes=rows_eval["with"],
                        no_residual_eval_successes=rows_eval["without"])
    prog.mark(f"round{r}/deploy", deployed_camera=camera,
              real_success=float(np.mean([x["success"] for x in rows])),
              real_successes=[x["success"] for x in rows],
              real_return=float(np.mean([x["return"] for x in rows])),
              camera_steps=int(sum(x["camera_steps"] for x in rows)),
              chosen_coords=[x["coords"] for x in rows],
              real_steps=real_steps(run),
              seconds=seconds_so_far(prog, r, deploy=t_eval - t0,
                                     evaluation=time.perf_counter() - t_eval))
