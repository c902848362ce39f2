"""Evaluation only: what the loop and the benchmarks measure against the real twin's hidden truth.

The learning side of twinrl sees only what a real robot would give it (recorded transitions and
images). Judging it needs the truth the real twin hides: its true parameters (to score
identification) and a policy trained on them (the *oracle*, to score returns). Those reads live
here, the only module outside ``twinrl/real`` allowed to call ``RealTwin.oracle`` (a test greps the
package for it); nothing here is ever fed back into learning.

The loop's real twin is served in another process (``twinrl.real.remote.TwinClient``) with its
perturbation seeded by a secret salt kept in the run's evaluation directory; the functions here
take that file as ``secret`` and rebuild the same twin in this process, where its truth can be
read. ``secret=None`` is the public-seed twin ``make_real(env_name, seed=seed)``.
"""

from __future__ import annotations

import jax
import numpy as np

__all__ = ["rebuild_twin", "param_errors", "param_error_sets", "sysid_errors", "real_return", "policy_real_return",
           "oracle_return",
           "visual_errors", "hand_eye_errors", "grasp_errors", "deployed_success"]


def rebuild_twin(env_name, seed, perturbation=None, secret=None, **kwargs):
    """The real twin ``(env_name, seed)`` in this process: the one a ``TwinClient`` with the same
    ``secret`` and ``perturbation`` talks to."""
    from twinrl.real.twin import make_real

    if secret is not None:
        from twinrl.real.remote import hidden_perturbation

        perturbation = hidden_perturbation(env_name, seed, secret, perturbation)
    return make_real(env_name, seed=seed, perturbation=perturbation, **kwargs)


def _truth(env_name, seed, perturbation=None, secret=None):
    """The hidden truth of the real twin ``(env_name, seed)`` (``RealTwin.oracle()``: its true
    parameters, perturbation and model), for evaluation only."""
    twin = rebuild_twin(env_name, seed, perturbation, secret)
    try:
        return twin.oracle()
    finally:
        twin.close()


def param_errors(env_name, seed, result, perturbation=None, secret=None, *,
                 every: bool = False) -> dict[str, float]:
    """Relative error of every fitted parameter against the twin's hidden truth (parameters the
    data fix only up to a common scale are compared after that scale: ``aligned_rel_err``;
    parameters left at nominal as not identifiable are left out, unless ``every``: then every
    fitted parameter is, whatever its status)."""
    identified, everyone = param_error_sets(env_name, seed, result, perturbation, secret)
    return everyone if every else identified


def param_error_sets(env_name, seed, result, perturbation=None, secret=None, *, truth=None
                     ) -> tuple[dict[str, float], dict[str, float]]:
    """``param_errors`` and ``param_errors(..., every=True)`` from one look at the truth
    (``truth``: a ``_truth(...)`` already taken)."""
    from twinrl.real2sim.sysid import compare_to_truth

    truth = truth or _truth(env_name, seed, perturbation, secret)
    rows = [row for row in compare_to_truth(result, truth.params, truth.perturbation.latency_steps)
            if not str(row.get("status", "")).startswith("known")]
    error = {row["parameter"]: float(row.get("aligned_rel_err", row["rel_err"])) for row in rows}
    return ({row["parameter"]: error[row["parameter"]] for row in rows
             if not str(row.get("status", "")).startswith("not ident")}, error)


def servo_speed_errors(env, params, env_name, seed, perturbation=None, secret=None, *,
                       truth=None) -> dict[str, float]:
    """Relative error per joint (``"joint1"``..) of the servo speeds ``env.servo_speed(params)``
    (an arm task's: what its controller is calibrated with) against the real twin's true ones
    (``truth``: a ``_truth(...)`` already taken)."""
    truth = truth or _truth(env_name, seed, perturbation, secret)
    want, got = env.servo_speed(truth.params), env.servo_speed(params)
    return {f"joint{i + 1}": float(abs(g / w - 1.0)) for i, (g, w) in enumerate(zip(got, want))}


def sysid_errors(env, result, env_name, seed, perturbation=None, secret=None
                 ) -> dict[str, dict[str, float]]:
    """An arm loop's sysid ``result`` against the hidden truth, from one look at it:
    ``param_rel_error`` and ``param_rel_error_all`` (``param_error_sets``) and
    ``servo_speed_rel_error`` (``servo_speed_errors`` of the identified parameters)."""
    truth = _truth(env_name, seed, perturbation, secret)
    identified, everyone = param_error_sets(env_name, seed, result, truth=truth)
    return {"param_rel_error": identified, "param_rel_error_all": everyone,
            "servo_speed_rel_error": servo_speed_errors(env, result.system.params, env_name, seed,
                                                        truth=truth)}


def visual_errors(env_name: str, twin_seed: int, summary: dict, secret=None) -> dict[str, float]:
    """Errors of a visual fit (``twinrl.real2sim.visual.visual_sysid``'s summary) against the
    hidden truth of the real twin ``make_real(env_name, seed=twin_seed)`` the frames came from:
    camera position (mm) and rotation (deg) against its offset camera; the object's position
    offset (mm; the frames' recorded states are where the object really was, so the truth is 0),
    size (largest relative error, %) and colour (largest channel error, /255) against its true
    model."""
    import mujoco

    from twinrl import envs
    from twinrl.render import Camera

    model = _truth(env_name, twin_seed, secret=secret).model
    out: dict[str, float] = {}
    if "camera" in summary:
        c = summary["camera"]
        d = mujoco.MjData(model)
        mujoco.mj_forward(model, d)
        true = Camera.from_mujoco(model, d, summary["camera_name"])
        A = np.asarray(true.xmat, np.float64)
        q = np.asarray(c["quat"], np.float64)
        B = np.empty(9)
        mujoco.mju_quat2Mat(B, q / np.linalg.norm(q))
        cos = (np.trace(A.T @ B.reshape(3, 3)) - 1) / 2
        out["camera_pos_err_mm"] = float(np.linalg.norm(np.asarray(c["pos"]) - np.asarray(
            true.pos)) * 1e3)
        out["camera_rot_err_deg"] = float(np.rad2deg(np.arccos(np.clip(cos, -1, 1))))
    if "object" in summary:
        o = summary["object"]
        gid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, o["geom"])
        size = np.asarray(model.geom_size[gid], np.float64)
        used = size > 0
        out["object_pos_err_mm"] = float(np.linalg.norm(o["pos_offset"]) * 1e3)
        out["object_size_err_pct"] = float(np.max(np.abs(
            np.asarray(o["size"])[used] / size[used] - 1)) * 100)
        out["object_colour_err_255"] = float(np.max(np.abs(
            np.asarray(o["rgb"]) - model.geom_rgba[gid, :3])) * 255)
    return out


def real_return(env_name, seed, policy_dir, episodes, perturbation=None, secret=None):
    """Mean return of a policy checkpoint on a fresh copy of the real twin (same hidden
    perturbation), not recorded and not counted."""
    from twinrl.learn.checkpoint import load_policy

    net, params, _ = load_policy(policy_dir)
    f = jax.jit(net.apply)
    return policy_real_return(env_name, seed, lambda o: f(params, o), episodes, perturbation,
                              secret)


def policy_real_return(env_name, seed, act, episodes, perturbation=None, secret=None):
    """Mean return of ``act: obs -> action`` over ``episodes`` episodes of a fresh copy of the real
    twin, started from the same states as ``real_return``'s (so two policies compare on equal
    terms), not recorded and not counted."""
    twin = rebuild_twin(env_name, seed, perturbation, secret)
    rets = []
    try:
        for e in range(episodes):
            obs, _ = twin.reset(seed=10_000 + e)
            done, ret = False, 0.0
            while not done:
                obs, rw, term, trunc, _ = twin.step(np.asarray(act(obs), np.float32))
                ret, done = ret + rw, term or trunc
            rets.append(ret)
    finally:
        twin.close()
    return float(np.mean(rets))


def oracle_return(env_name, seed, out, config, progress, perturbation=None, secret=None) -> float:
    """The oracle: trained in a simulator with the twin's true parameters (evaluation only)."""
    from twinrl import envs
    from twinrl.learn.runner import continue_run

    truth = _truth(env_name, seed, perturbation, secret).params
    env = envs.make(env_name, params=truth)
    if not (out / "policy" / "checkpoint.json").exists():
        continue_run(env_name, config.algo, out, seed=seed, epochs=config.epochs,
                     progress=progress, env=env, checkpoint_every=config.checkpoint_every)
    return real_return(env_name, seed, out / "policy", config.eval_episodes, perturbation, secret)


def hand_eye_errors(env_name, seed, mount, perturbation=None, secret=None) -> dict[str, float]:
    """The camera mount's hand-eye calibration (``CameraMount.pos_offset``/``rot_offset``, in the
    commanded camera frame) against the real twin's hidden camera offset: position (mm) and
    rotation (deg) errors, and what they were before calibration (the nominal zero offset)."""
    import mujoco

    from twinrl.real.perturbation import rotvec_quat

    p = _truth(env_name, seed, perturbation, secret).perturbation

    def rot_err(a, b):
        qa, qb = rotvec_quat(np.asarray(a, np.float64)), rotvec_quat(np.asarray(b, np.float64))
        d = np.empty(4)
        mujoco.mju_mulQuat(d, np.array([qa[0], -qa[1], -qa[2], -qa[3]]), qb)
        return float(np.rad2deg(2 * np.arccos(np.clip(abs(d[0]), -1.0, 1.0))))

    true_pos = np.asarray(p.camera_pos_offset, np.float64)
    return {"hand_eye_pos_err_mm": float(np.linalg.norm(np.asarray(mount.pos_offset) - true_pos)
                                         * 1e3),
            "hand_eye_rot_err_deg": rot_err(mount.rot_offset, p.camera_rot_offset),
            "uncalibrated_pos_err_mm": float(np.linalg.norm(true_pos) * 1e3),
            "uncalibrated_rot_err_deg": rot_err(np.zeros(3), p.camera_rot_offset)}


def grasp_errors(env_name, seed, pos_offset, rot_offset, perturbation=None,
                 secret=None) -> dict[str, float]:
    """An identified grasp of the tool (``ArmTask.set_grasp``'s offsets) against the real twin's
    hidden one: the error (mm) of the controller's tool centre point it puts in the hand (what
    the task's success is judged at), of the tool frame's origin, and its rotation error (deg;
    a turn about a round tool's own axis included, though no image shows it), with the same
    for the nominal grasp (none identified)."""
    import mujoco

    from twinrl import envs
    from twinrl.real.perturbation import rotvec_quat

    p = _truth(env_name, seed, perturbation, secret).perturbation
    tcp = np.asarray(envs.make(env_name).controller.tcp, np.float64)

    def mat(rotvec):
        m = np.empty(9)
        mujoco.mju_quat2Mat(m, rotvec_quat(np.asarray(rotvec, np.float64)))
        return m.reshape(3, 3)

    def errs(pos, rot):
        Rt, Rf = mat(p.tool_rot_offset), mat(rot)
        tip_t = np.asarray(p.tool_pos_offset, np.float64) + Rt @ tcp
        tip_f = np.asarray(pos, np.float64) + Rf @ tcp
        qt, qf = rotvec_quat(p.tool_rot_offset), rotvec_quat(np.asarray(rot, np.float64))
        d = np.empty(4)
        mujoco.mju_mulQuat(d, np.array([qt[0], -qt[1], -qt[2], -qt[3]]), qf)
        return (float(np.linalg.norm(tip_f - tip_t) * 1e3),
                float(np.linalg.norm(np.asarray(pos) - np.asarray(p.tool_pos_offset)) * 1e3),
                float(np.rad2deg(2 * np.arctan2(np.linalg.norm(d[1:]), abs(d[0])))))

    fit, nominal = errs(pos_offset, rot_offset), errs(np.zeros(3), np.zeros(3))
    return {"grasp_tcp_err_mm": fit[0], "grasp_pos_err_mm": fit[1], "grasp_rot_err_deg": fit[2],
            "nominal_tcp_err_mm": nominal[0], "nominal_pos_err_mm": nominal[1],
            "nominal_rot_err_deg": nominal[2]}


def deployed_success(env_name, seed, deployer, config, perturbation=None, secret=None,
                     size: int = 64) -> dict:
    """``deployer.run`` (``twinrl.sim2real.active.Deployer``) on the real twin in this process,
    nothing recorded: the evaluation episodes of a deployed image actor (e.g. with the fixed
    camera, the baseline the chosen camera must beat)."""
    twin = rebuild_twin(env_name, seed, perturbation, secret, width=size, height=size)
    try:
        return deployer.run(twin, config, seed=50_000 + int(seed))
    finally:
        twin.close()
